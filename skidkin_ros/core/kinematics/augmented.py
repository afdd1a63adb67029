"""Augmented models: a base model plus named extensions, run by the shared integrator.

``AugmentedModel(base_name, extensions).bind(base, {ext: {param: value}})`` gives a
:class:`BoundAugmented`, a stateful twist source (see
:class:`skidkin_ros.core.odometry.integrator.StatefulTwistSource`) that the streaming integrator
(node, ``skidkin predict``) and the batch forms
(:func:`~skidkin_ros.core.odometry.integrator.stream_twists`,
:class:`skidkin_ros.core.calibration.predictor.SegmentPredictor` for fitting) run alike.

Per wheel sample i (stamp t_i, speeds held over [t_i, t_i+1)):

0. with ``backlash`` (a wheel-stage extension), the encoder speeds become the wheels' own
   through the drivetrain's play, a state per wheel (:mod:`.backlash`); everything below sees
   the wheels' speeds;
1. x_i = twist-stage extensions applied, in order, to the base twist b_i = J(k) [omega_l,
   omega_r], with the time since the drive (or the node) started and the base twist's rate
   r_i = (b_i - b_i-1) / max(t_i - t_i-1, MIN_RATE_STEP_S) (0 on the first sample, after a gap
   and at a repeated stamp);
2. with a lag extension (``first_order_lag`` on every component, ``forward_lag``, ``yaw_lag``,
   ``component_lags`` on some; tau > 0) each lagged component of the body twist y follows x
   exactly for a held input: y_i+1 = x_i + (y_i - x_i) d, d = exp(-dt / tau), and the twist
   integrated over the step is its mean x_i + (y_i - x_i) tau (1 - d) / dt; y starts at x on the
   first sample and after a gap; a component without a lag has y = x;
3. ``time_offset`` shifts what is published: the pose integrated up to t_i is the pose at
   t_i + offset (``output_offset_ns``).

Limitation: when a segment starts or ends inside a sample interval (a time offset that is not a
multiple of the sample period), the batch form uses the interval's mean twist for the partial
step; this only matters together with a lag.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import functools
from typing import Callable, Mapping, NamedTuple, Sequence

import numpy as np

from skidkin_ros.core.kinematics.backlash import play_speeds, PLAY_STATE, play_step
from skidkin_ros.core.kinematics.extensions import get_extension, ordered
from skidkin_ros.core.kinematics.models import BoundModel, get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.timeunits import s_to_ns
from skidkin_ros.errors import ParameterError

__all__ = ['AUGMENTED_NAME', 'MIN_RATE_STEP_S', 'AugmentedModel', 'AugmentedState',
           'BoundAugmented', 'first_order_response', 'lag_factors', 'lag_response',
           'rate_divisor', 'rate_steps', 'twist_rates']

AUGMENTED_NAME = 'augmented'
# A rate of change is measured over at least this long (s), as a wheel jump is (the wheel-jump
# rule's MIN_JUMP_INTERVAL_S is this constant): stamps microseconds apart would otherwise turn
# one encoder count into an enormous acceleration, and a rate term into an absurd twist.
MIN_RATE_STEP_S = 0.01


Triple = tuple[float, float, float]
_STILL: Triple = (0.0, 0.0, 0.0)


class AugmentedState(NamedTuple):
    """Streaming state: first stamp (ns), twist-stage output x and body twist y (held).

    ``t_ns`` and ``b``: the last sample's stamp and base twist (for the rate of the next one);
    ``r``: the base twist's rate at that sample (what the rate terms saw); ``play``: the
    backlash's state (:data:`~.backlash.PLAY_STATE`). A named tuple: the node builds one per
    sample, and a tuple is the cheapest to build.
    """

    t0_ns: int
    x: Triple
    y: Triple
    t_ns: int = 0
    b: Triple = _STILL
    r: Triple = _STILL
    play: tuple[float, float, float, float, float] = PLAY_STATE


def rate_divisor(step_s: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Return what a backward-difference rate divides by: the step, at least MIN_RATE_STEP_S.

    1 where the step is not usable (the rate is 0 there). The one home of the rule for every
    array form (:func:`twist_rates`, the tangents' rates, the online learner's paired steps);
    the node's scalar form, :meth:`BoundAugmented.begin`, does the same on floats.
    """
    return np.where(usable, np.maximum(step_s, MIN_RATE_STEP_S), 1.0)


def rate_steps(dt_s: np.ndarray, restart: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (usable, divisor) of the rates of (D, L) rows from sample i to i+1.

    ``dt_s[:, i]``: the step from sample i to i+1 (0 across a gap or a repeated stamp); a step is
    usable when it is positive and sample i+1 is no restart.
    """
    step = np.asarray(dt_s, dtype=float)[:, :-1]
    usable = (step > 0.0) & ~np.asarray(restart, bool)[:, 1:]
    return usable, rate_divisor(step, usable)


def twist_rates(base: np.ndarray, dt_s: np.ndarray, restart: np.ndarray) -> np.ndarray:
    """Return the base twist's backward-difference rate over (D, L) rows (D, L, 3).

    ``dt_s[:, i]``: the step from sample i to i+1 (0 across a gap or a repeated stamp); the rate
    is 0 on the first sample, after a restart and after a zero step, as the streaming form has it;
    a step shorter than :data:`MIN_RATE_STEP_S` counts as that long.
    """
    rate = np.zeros(base.shape)
    usable, safe = rate_steps(dt_s, restart)
    rate[:, 1:] = np.where(usable[..., None],
                           (base[:, 1:] - base[:, :-1]) / safe[..., None], 0.0)
    return rate


# The factors of the last few (steps, tau) pairs, for steps nobody writes to (a predictor's): a
# fit's evaluation and its Jacobian at the same parameters ask for them several times.
_LAG_FACTORS: list[tuple[np.ndarray, float, tuple[np.ndarray, np.ndarray]]] = []


def lag_factors(dt_s, tau_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Return (d, g): the decay exp(-dt/tau) and the mean factor tau (1 - d) / dt (1 at dt=0).

    For read-only steps the arrays are kept (read-only) and given again for the same tau.
    """
    dt = np.asarray(dt_s, dtype=float)
    kept = not dt.flags.writeable
    if kept:
        for known, tau, factors in _LAG_FACTORS:
            if known is dt and tau == tau_s:
                return factors
    ratio = dt / tau_s
    d = np.exp(-ratio)
    positive = dt > 0.0
    g = np.where(positive, -np.expm1(-ratio) / np.where(positive, ratio, 1.0), 1.0)
    if kept:
        d.setflags(write=False)
        g.setflags(write=False)
        _LAG_FACTORS.insert(0, (dt, tau_s, (d, g)))
        del _LAG_FACTORS[8:]
    return d, g


@dataclass(frozen=True)
class BoundAugmented:
    """A base model with extensions and all parameters fixed: what the integrator runs."""

    base: BoundModel
    extensions: tuple[str, ...]
    values: tuple[np.ndarray, ...]
    stateful: bool = field(default=True, init=False)

    name = AUGMENTED_NAME

    @property
    def geometry(self) -> Geometry:
        return self.base.geometry

    def _param(self, ext: str, param: str, default: float = 0.0) -> float:
        if ext not in self.extensions:
            return default
        index = self.extensions.index(ext)
        return float(self.values[index][get_extension(ext).param_names.index(param)])

    @functools.cached_property
    def taus(self) -> Triple:
        """Return the lag (s) of each twist component, 0 without one (read once)."""
        for name, k in zip(self.extensions, self.values):
            ext = get_extension(name)
            if ext.stage == 'dynamics':
                return ext.time_constants(k)
        return _STILL

    @functools.cached_property
    def half_play(self) -> float | None:
        """Return half the backlash's play (rad), None without a wheel-stage extension."""
        if 'backlash' not in self.extensions:
            return None
        return 0.5 * self._param('backlash', 'play_rad')

    @property
    def tau_s(self) -> float:
        """Return the longest lag in s, 0 without one."""
        return max(self.taus)

    @property
    def output_offset_s(self) -> float:
        return self._param('time_offset', 'offset_s')

    @property
    def output_offset_ns(self) -> int:
        return s_to_ns(self.output_offset_s)

    def extension_values(self) -> dict[str, dict[str, float]]:
        """Return {extension: {parameter: value}} in application order."""
        return {name: get_extension(name).mapping(k)
                for name, k in zip(self.extensions, self.values)}

    def memoryless(self, omega_l, omega_r, t_s, rate=None, base=None) -> np.ndarray:
        """Return x: the base twist after the twist-stage extensions (..., 3).

        ``rate``: the base twist's rate (..., 3), None: 0 (steady); ``base``: the base twist
        when the caller has it.
        """
        omega_l = np.asarray(omega_l, dtype=float)
        omega_r = np.asarray(omega_r, dtype=float)
        twist = self.base.twist(omega_l, omega_r) if base is None else base
        for name, k in zip(self.extensions, self.values):
            twist = get_extension(name).apply(k, twist, omega_l, omega_r, t_s, rate)
        return twist

    def twist(self, omega_l, omega_r) -> np.ndarray:
        """Return the steady-state twist at the drive start (what a stateless user sees)."""
        return self.memoryless(omega_l, omega_r, 0.0)

    # ---------------------------------------------------------------- streaming form
    @functools.cached_property
    def _scalar_chain(self) -> tuple[tuple[Callable, tuple[float, ...]], ...] | None:
        """Return each extension's float form and values, None if one has no float form."""
        chain = []
        for name, k in zip(self.extensions, self.values):
            function = get_extension(name).scalar_apply()
            if function is None:
                return None
            chain.append((function, tuple(np.asarray(k, dtype=float).tolist())))
        return tuple(chain)

    def scalar_memoryless(self, omega_l: float, omega_r: float, t_s: float,
                          rate: Triple = _STILL, base: Triple | None = None) -> Triple:
        """:meth:`memoryless` for one sample on plain floats (equal to it bit for bit)."""
        chain = self._scalar_chain
        if chain is None:  # an extension without a float form (the sparse correction)
            vx, vy, w = np.asarray(self.memoryless(
                omega_l, omega_r, t_s, np.asarray(rate, dtype=float),
                None if base is None else np.asarray(base, dtype=float)), dtype=float).tolist()
            return vx, vy, w
        vx, vy, w = self.base.scalar_twist(omega_l, omega_r) if base is None else base
        for function, k in chain:
            vx, vy, w = function(k, vx, vy, w, omega_l, omega_r, t_s, rate)
        return vx, vy, w

    def begin(self, state: AugmentedState | None, t_ns: int, omega_l: float, omega_r: float,
              restart: bool) -> tuple[AugmentedState, Triple]:
        """Take a new sample; return the new state and the body twist published now."""
        t0 = t_ns if state is None else state.t0_ns
        play = PLAY_STATE if state is None else state.play
        if self.half_play is not None:
            play, omega_l, omega_r = play_step(
                play, self.half_play, 0.0 if state is None else (t_ns - state.t_ns) * 1e-9,
                state is None or restart, float(omega_l), float(omega_r))
        b = self.base.scalar_twist(float(omega_l), float(omega_r))
        rate = _STILL
        if state is not None and not restart:
            step = (t_ns - state.t_ns) * 1e-9
            if step > 0.0:   # rate_divisor on floats
                step = step if step > MIN_RATE_STEP_S else MIN_RATE_STEP_S
                p = state.b
                rate = ((b[0] - p[0]) / step, (b[1] - p[1]) / step, (b[2] - p[2]) / step)
        x = self.scalar_memoryless(float(omega_l), float(omega_r), (t_ns - t0) * 1e-9, rate, b)
        if state is None or restart:
            y = x
        else:
            t_v, t_y, t_w = self.taus
            y = (state.y[0] if t_v > 0.0 else x[0], state.y[1] if t_y > 0.0 else x[1],
                 state.y[2] if t_w > 0.0 else x[2])
        return AugmentedState(t0, x, y, t_ns, b, rate, play), y

    def advance(self, state: AugmentedState, dt_s: float) -> tuple[AugmentedState, Triple]:
        """Return the state after holding for dt_s and the mean twist over that interval.

        :func:`lag_factors` and :func:`lag_response`'s sample loop on plain floats, per lagged
        component.
        """
        t_v, t_y, t_w = self.taus
        if not (t_v > 0.0 or t_y > 0.0 or t_w > 0.0):
            return state, state.x
        (x0, x1, x2), (y0, y1, y2) = state.x, state.y
        if t_v == t_y == t_w:  # one lag on the whole twist: its factors once
            ratio = dt_s / t_v
            d = float(np.exp(-ratio))
            g = -float(np.expm1(-ratio)) / ratio if dt_s > 0.0 else 1.0
            diff0, diff1, diff2 = y0 - x0, y1 - x1, y2 - x2
            held = (x0 + diff0 * d, x1 + diff1 * d, x2 + diff2 * d)
            mean = (x0 + diff0 * g, x1 + diff1 * g, x2 + diff2 * g)
        else:
            h0, m0 = _lag_step(x0, y0, t_v, dt_s)
            h1, m1 = _lag_step(x1, y1, t_y, dt_s)
            h2, m2 = _lag_step(x2, y2, t_w, dt_s)
            held, mean = (h0, h1, h2), (m0, m1, m2)
        return (AugmentedState(state.t0_ns, state.x, held, state.t_ns, state.b, state.r,
                               state.play), mean)

    def published(self, state: AugmentedState) -> Triple:
        """Return the body twist held at the end of an advanced interval (y; x without lag)."""
        return state.y

    # ---------------------------------------------------------------- batch form
    def intervals(self, t_ns: np.ndarray, omega_l: np.ndarray, omega_r: np.ndarray,
                  dt_s: np.ndarray, restart: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Batch form over (D, L): (published twists, mean twists over each interval)."""
        t_ns = np.asarray(t_ns, dtype=np.int64)
        t_s = (t_ns - t_ns[:, :1]) * 1e-9
        if self.half_play is not None:
            omega_l = play_speeds(omega_l, dt_s, restart, self.half_play)[0]
            omega_r = play_speeds(omega_r, dt_s, restart, self.half_play)[0]
        base = np.asarray(self.base.twist(np.asarray(omega_l, dtype=float),
                                          np.asarray(omega_r, dtype=float)), dtype=float)
        # the rate only matters to an extension that reads it
        rate = (twist_rates(base, dt_s, restart) if any(
            get_extension(name).uses_rate for name in self.extensions) else None)
        x = np.asarray(self.memoryless(omega_l, omega_r, t_s, rate, base), dtype=float)
        taus = self.taus
        if not max(taus) > 0.0:
            return x, x
        held, mean = x.copy(), x.copy()
        dt_s = np.asarray(dt_s, dtype=float)
        restart = np.asarray(restart, bool)
        for tau in sorted({t for t in taus if t > 0.0}):
            columns = [c for c in range(3) if taus[c] == tau]
            held[..., columns], mean[..., columns] = lag_response(x[..., columns], dt_s,
                                                                  restart, tau)
        return held, mean


def _lag_step(x: float, y: float, tau_s: float, dt_s: float) -> tuple[float, float]:
    """Return (y after dt_s, mean of y over dt_s) for one component; (x, x) without a lag."""
    if not tau_s > 0.0:
        return x, x
    ratio = dt_s / tau_s
    d = float(np.exp(-ratio))
    g = -float(np.expm1(-ratio)) / ratio if dt_s > 0.0 else 1.0
    diff = y - x
    return x + diff * d, x + diff * g


# The row plan of the last few (dt_s, restart) pairs: a fit runs the response on the same
# stamps hundreds of times, with other inputs and time constants.
_ROW_PLANS: list[tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...]]] = []


def _row_plan(dt_s: np.ndarray, restart: np.ndarray) -> tuple[np.ndarray, ...]:
    """Return (ends, steady, idle) of :func:`lag_response`'s rows (kept for the same arrays).

    A row is steady up to ``ends[r]``: a constant period, no restart; what follows is padding
    (repeated last stamps, dt = 0), over which the sample loop holds y as it is. Steady rows of
    one period go through one lfilter call together. A row that never moves on (every stamp
    repeated, padding of an empty drive) is idle: it holds y = x_0 (and counts as steady).
    """
    for known_dt, known_restart, plan in _ROW_PLANS:
        if known_dt is dt_s and known_restart is restart:
            return plan
    length = dt_s.shape[1]
    moving = dt_s > 0.0
    index = np.arange(length)
    ends = np.where(moving.any(axis=1), length - np.argmax(moving[:, ::-1], axis=1), 0)
    prefix = index[None, :] < ends[:, None]
    steady = ((ends > 2) & np.all(np.where(prefix, dt_s == dt_s[:, :1], True), axis=1)
              & np.all(np.where(prefix, True, dt_s == 0.0), axis=1)
              & ~np.any(np.asarray(restart, bool) & (index[None, :] <= ends[:, None]), axis=1))
    idle = (ends == 0) & ~np.any(np.asarray(restart, bool), axis=1)
    steady |= idle
    plan = (ends, steady, idle)
    # only arrays nobody writes to afterwards are worth keeping (a predictor's)
    if not (dt_s.flags.writeable or np.asarray(restart).flags.writeable):
        _ROW_PLANS.insert(0, (dt_s, restart, plan))
        del _ROW_PLANS[4:]
    return plan


def first_order_response(force: np.ndarray, d: np.ndarray, dt_s: np.ndarray,
                         restart: np.ndarray, first: np.ndarray, reset: np.ndarray | None
                         ) -> np.ndarray:
    """Run h_i+1 = d_i h_i + force_i over (K, D, L) tangents, as :func:`lag_response` runs.

    ``d``: (D, L) decays; ``first``: h_0 (K, D); after a restart h takes ``reset``'s value
    there (None: 0). A repeated stamp (d = 1, no force) holds h; rows of one period go
    through lfilter, the others through the sample loop.
    """
    from scipy.signal import lfilter

    count, drives, length = force.shape
    out = np.empty_like(force)
    ends, steady, idle = _row_plan(dt_s, restart)
    index = np.arange(length)
    out[:, idle] = first[:, idle, None]
    for decay in np.unique(d[steady & ~idle, 0]):
        rows = np.nonzero(steady & ~idle & (d[:, 0] == decay))[0]
        out[:, rows] = lfilter([0.0, 1.0], [1.0, -decay], force[:, rows], axis=-1,
                               zi=first[:, rows, None])[0]
        last = np.minimum(ends[rows], length - 1)
        tail = index[None, :] > last[:, None]
        edge = np.take_along_axis(out[:, rows], last[None, :, None].repeat(count, 0), -1)
        out[:, rows] = np.where(tail, edge, out[:, rows])
    rows = np.nonzero(~steady)[0]
    if rows.size:
        h = first[:, rows].copy()
        for i in range(length):
            out[:, rows, i] = h
            if i + 1 < length:
                h = d[rows, i] * h + force[:, rows, i]
                again = restart[rows, i + 1]
                h[:, again] = 0.0 if reset is None else reset[:, rows[again], i + 1]
    return out


def lag_response(x: np.ndarray, dt_s: np.ndarray, restart: np.ndarray,
                 tau_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Run the first-order response over (D, L) rows: (published twists, mean twists).

    Rows sampled at a constant period without restart go through scipy's lfilter (the same
    recursion, to rounding); the others through the sample loop the streaming form runs.
    """
    # scipy.signal takes a second to import: only the fits that reach this line pay it.
    from scipy.signal import lfilter

    d, g = lag_factors(dt_s, tau_s)
    held = np.empty_like(x)
    length = x.shape[1]
    index = np.arange(length)
    ends, steady, idle = _row_plan(dt_s, restart)
    held[idle] = x[idle, :1]
    for decay in np.unique(d[steady & ~idle, 0]):
        rows = np.nonzero(steady & ~idle & (d[:, 0] == decay))[0]
        held[rows] = lfilter([0.0, 1.0 - decay], [1.0, -decay], x[rows], axis=1,
                             zi=x[rows, :1].copy())[0]
        last = np.minimum(ends[rows], length - 1)
        tail = index[None, :] > last[:, None]
        edge = held[rows, last]
        held[rows] = np.where(tail[..., None], edge[:, None, :], held[rows])
    rows = np.nonzero(~steady)[0]
    if rows.size:
        xs, ds, rs, still = x[rows], d[rows], restart[rows], dt_s[rows] == 0.0
        y = xs[:, 0].copy()
        for i in range(length):
            held[rows, i] = y
            if i + 1 < length:
                x_i = xs[:, i]
                # a repeated stamp holds y as it is (the streaming form advances nothing)
                moved = np.where(still[:, i, None], y, x_i + (y - x_i) * ds[:, i, None])
                y = np.where(rs[:, i + 1, None], xs[:, i + 1], moved)
    mean = x + (held - x) * g[..., None]
    return held, mean


class AugmentedModel:
    """A base model name and an ordered list of extension names (the structure, no values)."""

    def __init__(self, base: str, extensions: Sequence[str]) -> None:
        self.base_model = get_model(base)
        self.extensions = ordered(extensions)

    @property
    def base(self) -> str:
        return self.base_model.name

    def bind(self, base: BoundModel | Mapping[str, float],
             values: Mapping[str, Mapping[str, float]] | None = None,
             geometry: Geometry | None = None) -> BoundAugmented:
        """Bind to a base BoundModel (or base values + geometry) and extension values."""
        if not isinstance(base, BoundModel):
            if geometry is None:
                raise ParameterError('bind: give a BoundModel, or base values and a geometry')
            base = self.base_model.bind(dict(base), geometry)
        if base.model.name != self.base:
            raise ParameterError(f'bind: base model is {base.model.name!r}, expected '
                                 f'{self.base!r}')
        values = dict(values or {})
        unknown = sorted(set(values) - set(self.extensions))
        if unknown:
            raise ParameterError(f'values given for extension(s) {unknown} that are not in the '
                                 f'model {list(self.extensions)}')
        vectors = tuple(get_extension(name).vector(dict(values.get(name, {})))
                        for name in self.extensions)
        return BoundAugmented(base, self.extensions, vectors)
