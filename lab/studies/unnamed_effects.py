"""Effects nobody named: random smooth functions of the wheel-speed state, diagnosed blind.

The effects study (:mod:`lab.studies.effects`) injects the simulator's catalogue, whose
every effect has an extension of the same form. This study draws effects from families outside
the catalogue, at random strengths and shapes, several per drive:

- ``saturating_slip``: v *= 1 - k tanh(|v| / v0) (slip that saturates with speed, the shape
  public slip models such as DRIVE's and track_odometry's describe);
- ``turn_slip``: omega *= 1 - k (1 - exp(-(omega / w0)^2)) (yaw slip growing with turn rate);
- ``turn_asymmetry``: omega *= 1 - k tanh(omega / w0) (a traction asymmetry: turns one way
  slip more than the other);
- ``curvature_loss``: v *= 1 - k tanh((omega L)^2 / (v^2 + c)) (forward speed lost in tight turns);
- ``yaw_drift``: omega += +-k v (1 + a v) (a drive that pulls to one side, more at speed);
- ``load_slip``: v *= 1 - k tanh(|dv/dt| / a0) (slip under acceleration or braking: load
  transfer), dv/dt of the true forward speed on the fine grid;
- ``rbf``: v *= 1 + sum_i a_i g_i, omega *= 1 + sum_i b_i g_i, g_i Gaussian bumps at random
  centres over (v / 1 m/s, omega / 2 rad/s) (a random smooth function).

A second group, ``--field``, draws one effect per drive from the field: effects modelled in
public odometry packages and papers that this project never named (:data:`FIELD_FAMILIES`),
reported apart from the random smooth draws:

- ``accel_gain``: v *= 1 - k dv/dt (a slip proportional to the signed acceleration: the adaptive
  ERPM gain of racing-stack wheel odometry);
- ``track_slip``: omega *= 1 - s, v *= 1 - c s, s = k tanh(|omega| / w0) (the translational slip
  that follows the angular slip, as track_odometry compensates it);
- ``tyre_radius``: each side's speed u *= 1 + k (u / 1 m/s)^2 (an effective radius that changes
  with speed: tyre deformation);
- ``backlash``: each side's wheel follows its motor (where the encoder is) with a play of k rad:
  after a reversal the motor turns through the play before the wheel moves (drivetrain backlash,
  a hysteresis, not a function of the present state);
- ``side_saturation``: each side's speed u *= 1 - k_side tanh(|u| / u0), k different per side
  (per-side traction saturation);
- ``slope_creep``: v_y += k |v| sin(heading - slope direction) (a lateral creep down a side
  slope: a function of the heading, not of the wheel speeds, which the residual model cannot
  represent; what diagnose says about it is the point).

Each case simulates two training and two evaluation drives (seeded, the scene alternating between
the simulator's two), with ICP-like ground truth (:func:`lab.studies.effects.icp_like`),
fits every plain model on the training drives, diagnoses ``edd_symmetric`` blind, and scores on
the evaluation drives: the best plain model, the diagnosed model, and the simulator's true model
(its effect pipeline on the wheel samples, :class:`~lab.studies.effects.SimulatorTruth`).
Effect-free cases count false corrections: anything added, and what it costs.

Run: ``python -m lab.studies.unnamed_effects --cases 6 --free 10`` (a few minutes on one
core; the scenes change only the lidar, which this study does not run: the ground truth is
ICP-like noise on the exact path).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
import math
import sys
import time
from typing import Iterator, Mapping, Sequence

from lab.studies.effects import GEOMETRY, icp_like, SIM_INTERVAL, SimulatorTruth, \
    TRUE_PARAMS
import numpy as np

from skidkin_ros.core.calibration.diagnosis import diagnose, DiagnosisOptions, DiagnosisResult
from skidkin_ros.core.calibration.evaluation import relative_errors
from skidkin_ros.core.calibration.fitting import fit_model
from skidkin_ros.core.calibration.predictor import SegmentPredictor
from skidkin_ros.core.calibration.segments import cut_segments
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.kinematics.models import get_model, MODEL_NAMES
from skidkin_ros.errors import DataError, ParameterError
from skidkin_ros.sim.effects import Effect, EffectInput, EffectSpec
from skidkin_ros.sim.scene import SCENE_NAMES
from skidkin_ros.sim.simulate import SimConfig, simulate

__all__ = ['FAMILIES', 'FIELD_FAMILIES', 'SmoothEffect', 'draw_effects', 'draw_field',
           'strong_ranges', 'UnnamedCase', 'run_case', 'run_study', 'summary', 'main']

# family -> (strength range, description)
FAMILIES: dict[str, tuple[tuple[float, float], str]] = {
    'saturating_slip': ((0.05, 0.3), 'v *= 1 - k tanh(|v| / v0)'),
    'turn_slip': ((0.1, 0.4), 'omega *= 1 - k (1 - exp(-(omega / w0)^2))'),
    'turn_asymmetry': ((0.05, 0.25), 'omega *= 1 - k tanh(omega / w0)'),
    'curvature_loss': ((0.05, 0.3), 'v *= 1 - k tanh((omega L)^2 / (v^2 + c))'),
    'yaw_drift': ((0.02, 0.1), 'omega += k v (1 + a v)'),
    'load_slip': ((0.05, 0.3), 'v *= 1 - k tanh(|dv/dt| / a0)'),
    'rbf': ((0.1, 0.3), 'v *= 1 + sum a_i g_i(v, omega); omega *= 1 + sum b_i g_i(v, omega)'),
}
# Effects of the field (module docstring): family -> (strength range, description).
FIELD_FAMILIES: dict[str, tuple[tuple[float, float], str]] = {
    'accel_gain': ((0.05, 0.15), 'v *= 1 - k dv/dt'),
    'track_slip': ((0.1, 0.3), 'omega *= 1 - s; v *= 1 - c s; s = k tanh(|omega| / w0)'),
    'tyre_radius': ((0.08, 0.2), 'u_side *= 1 +- k u_side^2'),
    'backlash': ((0.2, 0.6), 'wheel angle follows the motor angle with a play of k rad'),
    'side_saturation': ((0.1, 0.3), 'u_side *= 1 - k_side tanh(|u_side| / u0)'),
    'slope_creep': ((0.02, 0.06), 'v_y += k |v| sin(heading - slope direction)'),
}
ALL_FAMILIES = {**FAMILIES, **FIELD_FAMILIES}
# Effective track of the true model (its b_hat, in m: the virtual track): the sides' speeds from
# the twist, each the ground speed of its wheels (r alpha omega_side).
_TRACK_M = TRUE_PARAMS['b_hat']


@dataclass(frozen=True)
class SmoothEffect(Effect):
    """An effect outside the catalogue: a family, its strength and its shape parameters."""

    family: str = ''
    shape: tuple[float, ...] = ()
    stage_name: str = field(default='twist', init=False)

    def __post_init__(self) -> None:
        if self.family not in ALL_FAMILIES:
            raise ParameterError(f'unknown family {self.family!r}; known: '
                                 f'{", ".join(ALL_FAMILIES)}')
        if not (math.isfinite(self.strength) and self.strength >= 0.0):
            raise ParameterError(f'strength must be finite and >= 0, got {self.strength!r}')

    @property
    def spec(self) -> EffectSpec:
        (low, high), text = ALL_FAMILIES[self.family]
        return EffectSpec(self.name, 'twist', '-', low, high, text)

    @property
    def stage(self) -> str:
        return 'twist'

    @property
    def needs_pose(self) -> bool:
        return self.family == 'slope_creep'

    def mask(self, data: EffectInput) -> None:
        return None

    def describe(self) -> str:
        return f'{self.family}({self.strength:.3g})'

    def as_dict(self) -> dict:
        return {'name': self.name, 'strength': float(self.strength), 'family': self.family,
                'shape': list(self.shape)}

    def apply_twist(self, data: EffectInput) -> np.ndarray:
        if self.family in FIELD_FAMILIES:
            return _field_twist(self.family, float(self.strength), self.shape, data)
        twist = np.array(data.twist, dtype=float, copy=True)
        v, w = twist[:, 0], twist[:, 2]
        k, s = float(self.strength), self.shape
        family = self.family
        if family == 'saturating_slip':
            twist[:, 0] = v * (1.0 - k * np.tanh(np.abs(v) / s[0]))
        elif family == 'turn_slip':
            twist[:, 2] = w * (1.0 - k * (1.0 - np.exp(-(w / s[0]) ** 2)))
        elif family == 'turn_asymmetry':
            twist[:, 2] = w * (1.0 - k * np.tanh(w / s[0]))
        elif family == 'curvature_loss':
            twist[:, 0] = v * (1.0 - k * np.tanh((w * s[0]) ** 2 / (v * v + s[1])))
        elif family == 'yaw_drift':
            twist[:, 2] = w + s[1] * k * v * (1.0 + s[0] * v)
        elif family == 'load_slip':
            dv = np.gradient(v, data.t_s) if v.size > 2 else np.zeros_like(v)
            twist[:, 0] = v * (1.0 - k * np.tanh(np.abs(dv) / s[0]))
        elif family == 'rbf':
            bumps = len(s) // 4
            gain_v = np.zeros_like(v)
            gain_w = np.zeros_like(w)
            for i in range(bumps):
                cv, cw, a, b = s[4 * i:4 * i + 4]
                g = np.exp(-0.5 * (((v - cv) / 0.35) ** 2 + ((w / 2.0 - cw) / 0.35) ** 2))
                gain_v += a * k * g
                gain_w += b * k * g
            twist[:, 0] = v * (1.0 + gain_v)
            twist[:, 2] = w * (1.0 + gain_w)
        return twist


def _sides(twist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v, w = twist[:, 0], twist[:, 2]
    return v - 0.5 * _TRACK_M * w, v + 0.5 * _TRACK_M * w


def _with_sides(twist: np.ndarray, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    out = np.array(twist, dtype=float, copy=True)
    out[:, 0] = 0.5 * (left + right)
    out[:, 2] = (right - left) / _TRACK_M
    return out


def _backlash(u: np.ndarray, t_s: np.ndarray, play_rad: float) -> np.ndarray:
    """Return the wheel's ground speed when it follows its motor with a play of ``play_rad``."""
    radius = GEOMETRY.wheel_radius
    dt = np.diff(t_s, prepend=t_s[0])
    motor = np.cumsum(u * dt) / radius
    wheel = np.empty_like(motor)
    half = 0.5 * play_rad
    position = motor[0] if motor.size else 0.0
    for i, m in enumerate(motor.tolist()):
        position = min(max(position, m - half), m + half)
        wheel[i] = position
    speed = np.zeros_like(u)
    if u.size > 1:
        speed[1:] = np.diff(wheel) * radius / np.where(dt[1:] > 0, dt[1:], 1.0)
    return speed


def _field_twist(family: str, k: float, s: tuple[float, ...], data: EffectInput) -> np.ndarray:
    """Apply one of the field's effects (:data:`FIELD_FAMILIES`) to the twist."""
    twist = np.array(data.twist, dtype=float, copy=True)
    v, w = twist[:, 0], twist[:, 2]
    if family == 'accel_gain':
        dv = np.gradient(v, data.t_s) if v.size > 2 else np.zeros_like(v)
        twist[:, 0] = v * (1.0 - k * dv)
    elif family == 'track_slip':
        slip = k * np.tanh(np.abs(w) / s[0])
        twist[:, 2] = w * (1.0 - slip)
        twist[:, 0] = v * (1.0 - s[1] * slip)
    elif family == 'tyre_radius':
        left, right = _sides(twist)
        twist = _with_sides(twist, left * (1.0 + s[0] * k * left ** 2),
                            right * (1.0 + s[0] * k * right ** 2))
    elif family == 'backlash':
        left, right = _sides(twist)
        twist = _with_sides(twist, _backlash(left, data.t_s, k),
                            _backlash(right, data.t_s, k))
    elif family == 'side_saturation':
        left, right = _sides(twist)
        twist = _with_sides(twist, left * (1.0 - k * np.tanh(np.abs(left) / s[0])),
                            right * (1.0 - k * s[1] * np.tanh(np.abs(right) / s[0])))
    elif family == 'slope_creep':
        heading = data.pose_hint[:, 2] if data.pose_hint is not None else np.zeros_like(v)
        twist[:, 1] = twist[:, 1] + k * np.abs(v) * np.sin(heading - s[0])
    return twist


def _shape(family: str, rng: np.random.Generator) -> tuple[float, ...]:
    if family == 'track_slip':  # (w0, c)
        return (float(rng.uniform(0.3, 1.2)), float(rng.uniform(0.5, 1.0)))
    if family == 'tyre_radius':  # (grows or shrinks)
        return (float(rng.choice([-1.0, 1.0])),)
    if family == 'side_saturation':  # (u0, the other side's share of k)
        return (float(rng.uniform(0.2, 0.8)), float(rng.uniform(0.0, 0.6)))
    if family == 'slope_creep':  # (slope direction)
        return (float(rng.uniform(-math.pi, math.pi)),)
    if family in ('accel_gain', 'backlash'):
        return ()
    if family == 'saturating_slip':
        return (float(rng.uniform(0.2, 0.8)),)
    if family in ('turn_slip', 'turn_asymmetry'):
        return (float(rng.uniform(0.3, 1.2)),)
    if family == 'curvature_loss':
        return (float(rng.uniform(0.2, 0.4)), float(rng.uniform(0.02, 0.1)))
    if family == 'yaw_drift':  # (a, the side it pulls to)
        return (float(rng.uniform(-1.0, 1.0)), float(rng.choice([-1.0, 1.0])))
    if family == 'load_slip':
        return (float(rng.uniform(0.5, 2.0)),)
    bumps = int(rng.integers(2, 5))
    return tuple(float(x) for _ in range(bumps)
                 for x in (rng.uniform(-0.8, 0.8), rng.uniform(-0.8, 0.8),
                           rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0)))


def draw_effects(rng: np.random.Generator, count: int | None = None,
                 families: Sequence[str] = tuple(FAMILIES),
                 strength: tuple[float, float] | None = None) -> tuple[SmoothEffect, ...]:
    """Draw ``count`` (default 2 or 3) effects of distinct families, random strength and shape."""
    count = int(rng.integers(2, 4)) if count is None else count
    chosen = rng.choice(len(families), size=min(count, len(families)), replace=False)
    out = []
    for index in chosen:
        family = families[int(index)]
        low, high = strength or FAMILIES[family][0]
        value = float(rng.uniform(low, high))
        effect = SmoothEffect(f'unnamed_{family}', value, {}, family, _shape(family, rng))
        out.append(effect)
    return tuple(out)


def drives(effects: Sequence[Effect], seeds: Sequence[int], duration_s: float,
           scene: str) -> list[Drive]:
    """Simulate drives of the true model with ``effects`` and ICP-like ground truth."""
    out = []
    for seed in seeds:
        config = SimConfig(duration_s=duration_s, seed=seed, true_model='edd_symmetric',
                           true_params=TRUE_PARAMS, effects=tuple(effects), scene=scene)
        out.append(icp_like(simulate(config).drive(f'sim{seed}'),
                            np.random.default_rng(100 + seed)))
    return out


@dataclass(frozen=True)
class UnnamedCase:
    """One case: effects, scene, and median held-out eps_t of each model (m/m)."""

    index: int
    effects: tuple[SmoothEffect, ...]
    scene: str
    plain: dict[str, float]
    refitted: float
    augmented: float
    truth: float
    found: tuple[str, ...]
    dependence: tuple[str, ...]
    unexplained: tuple[str, ...]
    seconds: float

    @property
    def best_plain(self) -> float:
        return min(self.plain.values())

    @property
    def is_field(self) -> bool:
        return any(e.family in FIELD_FAMILIES for e in self.effects)

    def row(self) -> str:
        label = ' + '.join(e.describe() for e in self.effects) or 'none'
        found = ', '.join(self.found) or 'nothing'
        ratio_plain = self.augmented / self.best_plain if self.best_plain > 0 else math.nan
        ratio_true = self.augmented / self.truth if self.truth > 0 else math.nan
        return (f'| {self.index} | {label} | {self.scene} | {found} | {self.best_plain:.4f} '
                f'({min(self.plain, key=self.plain.get)}) | {self.augmented:.4f} | '
                f'{self.truth:.4f} | {ratio_plain:.2f} | {ratio_true:.2f} |')


def _median_eps_t(predictor: SegmentPredictor, source, min_path_m: float) -> float:
    eps_t, _ = relative_errors(predictor.errors(source), predictor.segments.path_m, min_path_m)
    return float(np.median(eps_t)) if eps_t.size else math.nan


def run_case(index: int, effects: Sequence[SmoothEffect], seed: int, duration_s: float = 90.0,
             options: DiagnosisOptions | None = None) -> UnnamedCase:
    """Simulate, fit the plain models, diagnose blind and score one case (module docstring)."""
    tic = time.perf_counter()
    scene = SCENE_NAMES[index % len(SCENE_NAMES)]
    base_seed = 1000 + 10 * seed
    train = drives(effects, [base_seed, base_seed + 1], duration_s, scene)
    evaluate = drives(effects, [base_seed + 2, base_seed + 3], duration_s, scene)
    options = options or DiagnosisOptions(interval=SIM_INTERVAL)
    segments = cut_segments(train, options.train_segments())
    predictor = SegmentPredictor(evaluate, cut_segments(evaluate, options.eval_segments()),
                                 interval=options.interval)
    plain = {}
    fitted = {}
    for name in MODEL_NAMES:
        try:
            fit = fit_model(name, GEOMETRY, segments)
        except DataError:
            continue
        fitted[name] = fit.values
        plain[name] = _median_eps_t(predictor, get_model(name).bind(fit.values, GEOMETRY),
                                    options.min_eval_path_m)
    result: DiagnosisResult = diagnose(train, evaluate, GEOMETRY,
                                       {'edd_symmetric': fitted['edd_symmetric']},
                                       'edd_symmetric', options)
    # An effect of the heading (slope creep) has no true model on segments: the segment
    # predictor starts each segment at its own origin, so the heading it would need is unknown.
    truth = (math.nan if any(e.needs_pose for e in effects) else
             _median_eps_t(predictor, SimulatorTruth(tuple(effects), duration_s,
                                                     options.interval),
                           options.min_eval_path_m))
    return UnnamedCase(index, tuple(effects), scene, plain, result.steps[1].stats_t.median,
                       result.steps[-1].stats_t.median, truth, result.extensions,
                       tuple(d.text() for d in result.residual_dependence()),
                       tuple(lead.signal for lead in result.unexplained),
                       time.perf_counter() - tic)


def strong_ranges(families: Mapping[str, tuple[tuple[float, float], str]]
                  ) -> dict[str, tuple[float, float]]:
    """Return the upper half of each family's strength range (effects at strengths that matter)."""
    return {name: (0.5 * (low + high), high) for name, ((low, high), _) in families.items()}


def draw_field(rng: np.random.Generator, index: int, strong: bool = False) -> SmoothEffect:
    """Draw the field family ``index`` (cycling) at a random strength and shape."""
    names = tuple(FIELD_FAMILIES)
    family = names[index % len(names)]
    low, high = (strong_ranges(FIELD_FAMILIES)[family] if strong
                 else FIELD_FAMILIES[family][0])
    return SmoothEffect(f'field_{family}', float(rng.uniform(low, high)), {}, family,
                        _shape(family, rng))


def run_study(cases: int, free: int, seed: int = 1, duration_s: float = 90.0,
              field_cases: int = 0, strong: bool = False) -> Iterator[UnnamedCase]:
    """Yield drives: ``cases`` with drawn effects, ``field_cases`` of the field, ``free`` none.

    A field drive has one effect of the field; ``strong`` draws strengths from the upper half of
    each family's range.
    """
    rng = np.random.default_rng(seed)
    for i in range(cases):
        effects = (draw_effects(rng) if not strong else tuple(
            draw_effects(rng, 1, (family,), strong_ranges(FAMILIES)[family])[0]
            for family in rng.choice(list(FAMILIES), size=int(rng.integers(2, 4)),
                                     replace=False)))
        yield run_case(i, effects, seed * 1000 + i, duration_s)
    field_rng = np.random.default_rng(seed + 7919)
    for i in range(field_cases):
        index = cases + i
        yield run_case(index, (draw_field(field_rng, i, strong),), seed * 1000 + index,
                       duration_s)
    for j in range(free):
        index = cases + field_cases + j
        yield run_case(index, (), seed * 1000 + index, duration_s)


HEADER = ('| # | effects (drawn) | scene | found | best plain eps_t (model) | diagnosed | true '
          'model | diagnosed / best plain | diagnosed / true |', '|' + '---|' * 9)


# A drive whose true model is above this fraction of the best plain model's error has an effect
# too weak for the 0.5x goal: even the truth does not reach it. Reported apart.
REACHABLE = 0.5


def _group_line(label: str, group: Sequence[UnnamedCase]) -> str:
    plain = np.array([r.augmented / r.best_plain for r in group])
    true = np.array([r.augmented / r.truth for r in group if r.truth > 0])
    text = (f'{label}: {len(group)}; diagnosed / best plain median {np.median(plain):.2f} '
            f'(<= 0.5 in {int((plain <= 0.5).sum())})')
    if true.size:
        text += (f'; diagnosed / true median {np.median(true):.2f} (<= 3 in '
                 f'{int((true <= 3.0).sum())} of {true.size})')
    return text


def summary(results: Sequence[UnnamedCase]) -> list[str]:
    """Return the goal lines: ratios with effects (drawn, weak, field), false corrections."""
    lines = []
    drawn = [r for r in results if r.effects and not r.is_field]
    field = [r for r in results if r.is_field]
    free = [r for r in results if not r.effects]
    reachable = [r for r in drawn if r.truth <= REACHABLE * r.best_plain]
    weak = [r for r in drawn if not r.truth <= REACHABLE * r.best_plain]
    if reachable:
        lines.append(_group_line('drawn effects, true model <= 0.5x best plain', reachable))
    if weak:
        lines.append(_group_line('drawn effects too weak for 0.5x (true model > 0.5x best '
                                 'plain)', weak) + '; true / best plain '
                     + ', '.join(f'{r.truth / r.best_plain:.2f}' for r in weak))
    for label, group in (('reachable', [r for r in field if r.truth <= REACHABLE * r.best_plain]),
                         ('too weak for 0.5x', [r for r in field
                                                if r.truth > REACHABLE * r.best_plain]),
                         ('with no true model', [r for r in field if not r.truth > 0])):
        if group:
            lines.append(_group_line(f'effects of the field, {label}', group))
    if free:
        added = [r for r in free if r.found]
        costs = [r.augmented / r.refitted - 1.0 for r in added if r.refitted > 0]
        lines.append(f'effect-free drives: {len(free)}; a correction added in {len(added)}'
                     + (f' (cost: {", ".join(f"{c:+.1%}" for c in costs)})' if costs else ''))
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog='python -m lab.studies.unnamed_effects',
        description='Diagnose drives with effects drawn outside the catalogue, blind, and '
        'effect-free drives to count false corrections.')
    parser.add_argument('--cases', type=int, default=6, help='drives with drawn effects')
    parser.add_argument('--free', type=int, default=10, help='effect-free drives')
    parser.add_argument('--field', type=int, default=0,
                        help='drives with one effect of the field each (cycling the families)')
    parser.add_argument('--strong', action='store_true',
                        help="draw strengths from the upper half of each family's range")
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--duration', type=float, default=90.0, help='seconds per drive')
    args = parser.parse_args(argv)
    out = sys.stdout
    out.write('\n'.join(HEADER) + '\n')
    results = []
    for case in run_study(args.cases, args.free, args.seed, args.duration, args.field,
                          args.strong):
        results.append(case)
        out.write(case.row() + '\n')
        for text in case.dependence + tuple(f'unexplained residual: signal {s}'
                                            for s in case.unexplained):
            out.write(f'|   | {text} | | | | | | | |\n')
        out.flush()
    for line in summary(results):
        out.write(line + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
