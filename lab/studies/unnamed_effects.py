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
from typing import Iterator, Sequence

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

__all__ = ['FAMILIES', 'SmoothEffect', 'draw_effects', 'UnnamedCase', 'run_case', 'run_study',
           'summary', 'main']

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


@dataclass(frozen=True)
class SmoothEffect(Effect):
    """An effect outside the catalogue: a family, its strength and its shape parameters."""

    family: str = ''
    shape: tuple[float, ...] = ()
    stage_name: str = field(default='twist', init=False)

    def __post_init__(self) -> None:
        if self.family not in FAMILIES:
            raise ParameterError(f'unknown family {self.family!r}; known: {", ".join(FAMILIES)}')
        if not (math.isfinite(self.strength) and self.strength >= 0.0):
            raise ParameterError(f'strength must be finite and >= 0, got {self.strength!r}')

    @property
    def spec(self) -> EffectSpec:
        (low, high), text = FAMILIES[self.family]
        return EffectSpec(self.name, 'twist', '-', low, high, text)

    @property
    def stage(self) -> str:
        return 'twist'

    @property
    def needs_pose(self) -> bool:
        return False

    def mask(self, data: EffectInput) -> None:
        return None

    def describe(self) -> str:
        return f'{self.family}({self.strength:.3g})'

    def as_dict(self) -> dict:
        return {'name': self.name, 'strength': float(self.strength), 'family': self.family,
                'shape': list(self.shape)}

    def apply_twist(self, data: EffectInput) -> np.ndarray:
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


def _shape(family: str, rng: np.random.Generator) -> tuple[float, ...]:
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
    truth = _median_eps_t(predictor, SimulatorTruth(tuple(effects), duration_s, options.interval),
                          options.min_eval_path_m)
    return UnnamedCase(index, tuple(effects), scene, plain, result.steps[1].stats_t.median,
                       result.steps[-1].stats_t.median, truth, result.extensions,
                       tuple(d.text() for d in result.residual_dependence()),
                       tuple(lead.signal for lead in result.unexplained),
                       time.perf_counter() - tic)


def run_study(cases: int, free: int, seed: int = 1, duration_s: float = 90.0
              ) -> Iterator[UnnamedCase]:
    """Yield ``cases`` drives with drawn effects, then ``free`` effect-free ones."""
    rng = np.random.default_rng(seed)
    for i in range(cases):
        yield run_case(i, draw_effects(rng), seed * 1000 + i, duration_s)
    for j in range(free):
        yield run_case(cases + j, (), seed * 1000 + cases + j, duration_s)


HEADER = ('| # | effects (drawn) | scene | found | best plain eps_t (model) | diagnosed | true '
          'model | diagnosed / best plain | diagnosed / true |', '|' + '---|' * 9)


def summary(results: Sequence[UnnamedCase]) -> list[str]:
    """Return the goal lines: ratios on drives with effects, false corrections without."""
    lines = []
    with_effects = [r for r in results if r.effects]
    free = [r for r in results if not r.effects]
    if with_effects:
        plain = np.array([r.augmented / r.best_plain for r in with_effects])
        true = np.array([r.augmented / r.truth for r in with_effects])
        lines.append(f'drives with unnamed effects: {len(with_effects)}; diagnosed / best plain '
                     f'median {np.median(plain):.2f} (<= 0.5 in {int((plain <= 0.5).sum())}); '
                     f'diagnosed / true median {np.median(true):.2f} (<= 3 in '
                     f'{int((true <= 3.0).sum())})')
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
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--duration', type=float, default=90.0, help='seconds per drive')
    args = parser.parse_args(argv)
    out = sys.stdout
    out.write('\n'.join(HEADER) + '\n')
    results = []
    for case in run_study(args.cases, args.free, args.seed, args.duration):
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
