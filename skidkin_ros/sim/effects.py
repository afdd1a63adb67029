"""Named, composable effects that make the true motion depart from a kinematic model.

Each effect has a strength (its one knob, with a unit and a plausible range) and acts at one
stage of the simulator's truth pipeline:

- ``wheels``: on the actual wheel speeds that drive the body (``time_offset``);
- ``twist``: on the body twist given by the true model (slips, skid, terrain);
- ``dynamics``: on the twist as a signal in time, applied last: a first-order response of the
  whole twist (``first_order_lag``), of the forward speed only (``forward_lag``) or of the yaw rate
  only (``yaw_lag``), and a body whose forward speed follows the wheels through a first-order
  response only while they speed up, and at once when they slow down (``acceleration_slip``:
  traction limits how fast the body gains speed, not how fast it loses it). These run on the
  simulator's fine time grid as continuous-time responses, not as the extensions' formulas (the
  acceleration slip extension is a derivative term of the wheel speeds held at 20 Hz).

All effects are causal, so simulating a prefix of a drive gives the prefix of the full drive.
``random_effect(rng)`` draws one effect and a strength within its range (seeded), for tests that
check that a diagnosis finds what was injected.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Callable, Sequence

import numpy as np

from skidkin_ros.core.kinematics.extensions import ratio_bump
from skidkin_ros.errors import ParameterError

__all__ = [
    'EFFECTS',
    'EFFECT_NAMES',
    'Effect',
    'EffectInput',
    'EffectSpec',
    'apply_effects',
    'make_effect',
    'random_effect',
]

# Speed (m/s) over which direction_asymmetry blends from forward to backward behaviour.
_DIRECTION_BLEND_M_S = 0.05
# Width of the ratio_yaw_slip bump around a speed ratio of 0.5 (one side turning ~2x the other).
_RATIO_PEAK = 0.5
_RATIO_WIDTH = 0.15
# speed_slip never removes more than this fraction of the forward speed.
_MAX_SPEED_SLIP = 0.8


@dataclass(frozen=True)
class EffectSpec:
    """What an effect is: name, stage, strength unit and range, and what it does."""

    name: str
    stage: str
    unit: str
    low: float
    high: float
    description: str


EFFECTS: dict[str, EffectSpec] = {spec.name: spec for spec in (
    EffectSpec('time_offset', 'wheels', 's', 0.02, 0.2,
               'true motion lags the wheel stamps by tau'),
    EffectSpec('first_order_lag', 'dynamics', 's', 0.05, 0.4,
               'body twist follows the wheel-implied twist through a first-order filter of '
               'time constant tau'),
    EffectSpec('speed_slip', 'twist', 's/m', 0.05, 0.3,
               'longitudinal slip k |v_x| growing with speed: v_x *= 1 - k |v_x|'),
    EffectSpec('ratio_yaw_slip', 'twist', '-', 0.1, 0.5,
               'yaw rate loses up to a fraction k when one side turns ~2x the other '
               '(the nonlinearity seen on snow)'),
    EffectSpec('lateral_skid', 'twist', 's', 0.02, 0.12,
               'lateral skid v_y += k v_x omega (centrifugal)'),
    EffectSpec('direction_asymmetry', 'twist', '-', 0.05, 0.3,
               'backward driving slips more: v_x *= 1 - k when reversing'),
    EffectSpec('terrain_regime', 'twist', '-', 0.1, 0.4,
               'v_x and omega lose a fraction k (omega: option yaw, when given) after a switch '
               'time (mode time), where x > boundary (mode region) or on every other stretch of '
               'period_m metres of path (mode alternate; period_spread: each stretch drawn '
               'uniformly within period_m (1 +- period_spread), from period_seed)'),
    # Appended (not inserted) so the strengths drawn for the effects above stay as they were.
    EffectSpec('forward_lag', 'dynamics', 's', 0.05, 0.4,
               'forward speed follows the wheel-implied forward speed through a first-order '
               'filter of time constant tau (v_y and omega at once)'),
    EffectSpec('yaw_lag', 'dynamics', 's', 0.05, 0.4,
               'yaw rate follows the wheel-implied yaw rate through a first-order filter of '
               'time constant tau (v_x and v_y at once)'),
    EffectSpec('acceleration_slip', 'dynamics', 's', 0.05, 0.25,
               'forward speed lags the wheels by a first-order response of time constant tau '
               'while they speed up, and follows them at once when they slow down'),
)}
EFFECT_NAMES: tuple[str, ...] = tuple(EFFECTS)
_STAGE_ORDER = {'wheels': 0, 'twist': 1, 'dynamics': 2}


@dataclass(frozen=True)
class EffectInput:
    """What an effect sees, on the simulator's fine time grid (N steps).

    t_s: time since the drive start (s); omega_l/omega_r: actual wheel speeds (rad/s) driving
    the body; twist: (N, 3) body twist (v_x, v_y, omega); pose_hint: (N, 3) poses of the twist
    before this stage (for regions), or None; duration_s: planned drive duration.
    """

    t_s: np.ndarray
    omega_l: np.ndarray
    omega_r: np.ndarray
    twist: np.ndarray
    pose_hint: np.ndarray | None
    duration_s: float


@dataclass(frozen=True)
class Effect:
    """One named effect with its strength; ``options`` tune the terrain regime.

    terrain_regime options: mode ('time', 'region' or 'alternate'), switch_frac (fraction of the
    duration after which the regime starts, mode time), boundary_x_m (regime where x > boundary,
    mode region), period_m (mode alternate: the regime on every other stretch of that much path,
    the first stretch off), period_spread (mode alternate: each stretch's length drawn uniformly
    within period_m (1 +- period_spread) instead, 0 <= spread < 1, default 0) and period_seed (the
    draws' seed, default 0), yaw (the fraction omega loses, default the strength: a ground that
    slips in translation and in yaw by different amounts).
    """

    name: str
    strength: float
    options: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        spec = EFFECTS.get(self.name)
        if spec is None:
            raise ParameterError(f'unknown effect {self.name!r}; known effects are: '
                                 f'{", ".join(EFFECT_NAMES)}')
        if not (isinstance(self.strength, (int, float)) and math.isfinite(self.strength)
                and self.strength >= 0.0):
            raise ParameterError(f'effect {self.name}: strength must be a finite number >= 0 '
                                 f'{spec.unit} (typical {spec.low:g}..{spec.high:g}), got '
                                 f'{self.strength!r}')
        allowed = {'terrain_regime': {'mode', 'switch_frac', 'boundary_x_m', 'period_m',
                                      'period_spread', 'period_seed', 'yaw'}}.get(self.name, set())
        unknown = sorted(set(self.options) - allowed)
        if unknown:
            raise ParameterError(f'effect {self.name}: unknown option(s) {unknown}; allowed: '
                                 f'{sorted(allowed)}')
        if self.options.get('mode', 'time') not in ('time', 'region', 'alternate'):
            raise ParameterError("terrain_regime mode must be 'time', 'region' or 'alternate'")
        if not float(self.options.get('period_m', 5.0)) > 0.0:
            raise ParameterError('terrain_regime period_m must be > 0 m')
        if not 0.0 <= float(self.options.get('period_spread', 0.0)) < 1.0:
            raise ParameterError('terrain_regime period_spread must be >= 0 and < 1 (a share of '
                                 f"period_m), got {self.options['period_spread']!r}")

    @property
    def spec(self) -> EffectSpec:
        return EFFECTS[self.name]

    @property
    def stage(self) -> str:
        return self.spec.stage

    @property
    def needs_pose(self) -> bool:
        return self.name == 'terrain_regime' and self.options.get('mode', 'time') == 'region'

    def describe(self) -> str:
        """Return a one-line text: name, strength with unit, and options."""
        extra = ''.join(f', {key}={value}' for key, value in sorted(self.options.items()))
        return f'{self.name}({self.strength:.4g} {self.spec.unit}{extra})'

    def as_dict(self) -> dict:
        return {'name': self.name, 'strength': float(self.strength),
                'unit': self.spec.unit, **self.options}

    def mask(self, data: EffectInput) -> np.ndarray | None:
        """Return where the terrain regime is active (fine grid), None for other effects."""
        if self.name != 'terrain_regime':
            return None
        if self.options.get('mode', 'time') == 'time':
            return data.t_s >= float(self.options.get('switch_frac', 0.5)) * data.duration_s
        if self.options['mode'] == 'alternate':
            return _alternating(data, float(self.options.get('period_m', 5.0)),
                                float(self.options.get('period_spread', 0.0)),
                                int(self.options.get('period_seed', 0)))
        return data.pose_hint[:, 0] > float(self.options.get('boundary_x_m', 0.0))

    def apply_wheels(self, data: EffectInput) -> tuple[np.ndarray, np.ndarray]:
        """Return the wheel speeds that drive the body after this effect (wheels stage)."""
        tau = float(self.strength)
        lagged_t = data.t_s - tau
        return (np.interp(lagged_t, data.t_s, data.omega_l),
                np.interp(lagged_t, data.t_s, data.omega_r))

    def apply_twist(self, data: EffectInput) -> np.ndarray:
        """Return the body twist after this effect (twist and dynamics stages)."""
        twist = np.array(data.twist, dtype=float, copy=True)
        v_x, omega = twist[:, 0], twist[:, 2]
        k = float(self.strength)
        if self.name == 'first_order_lag':
            return _first_order(twist, data.t_s, k)
        if self.name in ('forward_lag', 'yaw_lag'):
            column = 0 if self.name == 'forward_lag' else 2
            twist[:, column] = _first_order(twist[:, column:column + 1], data.t_s, k)[:, 0]
            return twist
        if self.name == 'acceleration_slip':
            twist[:, 0] = _lag_while_speeding_up(v_x, data.t_s, k)
            return twist
        if self.name == 'speed_slip':
            twist[:, 0] = v_x * (1.0 - np.minimum(k * np.abs(v_x), _MAX_SPEED_SLIP))
        elif self.name == 'ratio_yaw_slip':
            bump = ratio_bump(data.omega_l, data.omega_r, _RATIO_PEAK, _RATIO_WIDTH)
            twist[:, 2] = omega * (1.0 - k * bump)
        elif self.name == 'lateral_skid':
            twist[:, 1] = twist[:, 1] + k * v_x * omega
        elif self.name == 'direction_asymmetry':
            reverse = np.clip(-v_x / _DIRECTION_BLEND_M_S, 0.0, 1.0)
            twist[:, 0] = v_x * (1.0 - k * reverse)
        elif self.name == 'terrain_regime':
            on = self.mask(data)
            twist[:, 0] = v_x * np.where(on, 1.0 - k, 1.0)
            twist[:, 2] = omega * np.where(on, 1.0 - float(self.options.get('yaw', k)), 1.0)
        return twist


def _alternating(data: EffectInput, period_m: float, spread: float = 0.0,
                 seed: int = 0) -> np.ndarray:
    """Return True on every other stretch of ``period_m`` metres of path (the first: False).

    The path is the wheel-implied one (the twist before this effect), integrated on the fine
    grid: causal, so a prefix of a drive has the prefix of its mask. With ``spread`` > 0 each
    stretch lasts a length drawn uniformly within ``period_m`` (1 +- spread) (``seed``: the
    draws, the same for every prefix of the drive).
    """
    speed = np.hypot(data.twist[:, 0], data.twist[:, 1])
    dt_s = np.diff(data.t_s, append=data.t_s[-1])
    path = np.concatenate([[0.0], np.cumsum(speed * dt_s)[:-1]])
    if spread <= 0.0:
        return (np.floor(path / period_m).astype(np.int64) % 2) == 1
    rng = np.random.default_rng(seed)
    lengths: list[float] = []
    total = 0.0
    while total <= path[-1]:
        lengths.extend(period_m * (1.0 + spread * rng.uniform(-1.0, 1.0, 64)))
        total = float(np.sum(lengths))
    ends = np.cumsum(lengths)
    return (np.searchsorted(ends, path, side='right') % 2) == 1


def _first_order(signal: np.ndarray, t_s: np.ndarray, tau_s: float) -> np.ndarray:
    """Filter each column through 1 / (tau s + 1), exact for inputs held over each step."""
    if tau_s <= 0.0 or signal.shape[0] < 2:
        return signal
    dt_s = float(np.median(np.diff(t_s)))
    decay = math.exp(-dt_s / tau_s)
    from scipy.signal import lfilter  # scipy.signal: about 1 s of CPU to import

    return lfilter([0.0, 1.0 - decay], [1.0, -decay], signal, axis=0)


def _lag_while_speeding_up(target: np.ndarray, t_s: np.ndarray, tau_s: float) -> np.ndarray:
    """Follow ``target`` through 1 / (tau s + 1) while it outruns the output, else at once.

    The body starts settled; each fine step, if the target is faster than the body in the same
    direction the body closes the gap by the exact first-order step, otherwise it takes the
    target's value.
    """
    if tau_s <= 0.0 or target.size < 2:
        return target
    dt_s = float(np.median(np.diff(t_s)))
    keep = math.exp(-dt_s / tau_s)
    values = target.tolist()
    out = [0.0] * len(values)
    body = values[0]
    for i, goal in enumerate(values):
        out[i] = body
        if goal * body >= 0.0 and abs(goal) > abs(body):
            body = goal + (body - goal) * keep
        else:
            body = goal
    return np.asarray(out)


def make_effect(name: str, strength: float | None = None, **options) -> Effect:
    """Return an effect by name; strength defaults to the middle of its range."""
    spec = EFFECTS.get(name)
    if spec is None:
        raise ParameterError(f'unknown effect {name!r}; known effects are: '
                             f'{", ".join(EFFECT_NAMES)}')
    value = 0.5 * (spec.low + spec.high) if strength is None else strength
    return Effect(name, value, dict(options))


def random_effect(rng: np.random.Generator, names: Sequence[str] | None = None) -> Effect:
    """Draw one effect (uniformly among ``names``, default all) and a strength in its range."""
    pool = tuple(names) if names else EFFECT_NAMES
    name = pool[int(rng.integers(len(pool)))]
    spec = EFFECTS[name]
    return make_effect(name, float(rng.uniform(spec.low, spec.high)))


def apply_effects(effects: Sequence[Effect], t_s: np.ndarray, omega_l: np.ndarray,
                  omega_r: np.ndarray, twist_fn: Callable[[np.ndarray, np.ndarray], np.ndarray],
                  rollout_fn: Callable[[np.ndarray], np.ndarray], duration_s: float,
                  ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Run the truth pipeline: wheel effects, the true model, twist effects, dynamics.

    twist_fn maps wheel speeds to the true model's twist (N, 3); rollout_fn integrates a twist
    on the fine grid to poses (N, 3) (for region-dependent effects). Returns the final twist and
    a dict of masks (e.g. where the terrain regime was active).
    """
    ordered = sorted(effects, key=lambda effect: _STAGE_ORDER[effect.stage])
    masks: dict[str, np.ndarray] = {}
    data = EffectInput(t_s, omega_l, omega_r, np.zeros((t_s.size, 3)), None, duration_s)
    for effect in (e for e in ordered if e.stage == 'wheels'):
        left, right = effect.apply_wheels(data)
        data = EffectInput(t_s, left, right, data.twist, None, duration_s)
    twist = np.asarray(twist_fn(data.omega_l, data.omega_r), dtype=float)
    for effect in (e for e in ordered if e.stage != 'wheels'):
        hint = rollout_fn(twist) if effect.needs_pose else None
        data = EffectInput(t_s, data.omega_l, data.omega_r, twist, hint, duration_s)
        mask = effect.mask(data)
        if mask is not None:
            masks[effect.name] = mask
        twist = effect.apply_twist(data)
    return twist, masks
