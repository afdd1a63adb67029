"""Augmented models: a base model plus named extensions, run by the shared integrator.

``AugmentedModel(base_name, extensions).bind(base, {ext: {param: value}})`` gives a
:class:`BoundAugmented`, a stateful twist source (see
:class:`skidkin_ros.core.integrator.StatefulTwistSource`) that the streaming integrator (node,
``skidkin predict``) and the batch forms (:func:`~skidkin_ros.core.integrator.stream_twists`,
:class:`SegmentPredictor` for fitting) run alike.

Per wheel sample i (stamp t_i, speeds held over [t_i, t_i+1)):

1. x_i = twist-stage extensions applied, in order, to the base twist J(k) [omega_l, omega_r],
   with the time since the drive (or the node) started;
2. with ``first_order_lag`` (tau > 0) the body twist y follows x exactly for a held input:
   y_i+1 = x_i + (y_i - x_i) d, d = exp(-dt / tau), and the twist integrated over the step is its
   mean x_i + (y_i - x_i) tau (1 - d) / dt; y starts at x on the first sample and after a gap;
   without a lag y = x;
3. ``time_offset`` shifts what is published: the pose integrated up to t_i is the pose at
   t_i + offset (``output_offset_ns``).

Limitation: when a segment starts or ends inside a sample interval (a time offset that is not a
multiple of the sample period), the batch form uses the interval's mean twist for the partial
step; this only matters together with a lag.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import functools
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy.signal import lfilter

from skidkin_ros.core.drive import Drive
from skidkin_ros.core.extensions import get_extension, ordered
from skidkin_ros.core.integrator import body_increment, compose, is_stateful, rollout_columns
from skidkin_ros.core.models import BoundModel, get_model
from skidkin_ros.core.segments import segment_frame_error, SegmentSet
from skidkin_ros.core.specs import Geometry
from skidkin_ros.errors import ParameterError

__all__ = ['AUGMENTED_NAME', 'AugmentedModel', 'AugmentedState', 'BoundAugmented',
           'SegmentPredictor', 'lag_factors', 'lag_response', 'relative_errors']

AUGMENTED_NAME = 'augmented'


@dataclass(frozen=True)
class AugmentedState:
    """Streaming state: first stamp (ns), twist-stage output x and body twist y (held)."""

    t0_ns: int
    x: tuple[float, float, float]
    y: tuple[float, float, float]


def lag_factors(dt_s, tau_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Return (d, g): the decay exp(-dt/tau) and the mean factor tau (1 - d) / dt (1 at dt=0)."""
    dt = np.asarray(dt_s, dtype=float)
    ratio = dt / tau_s
    d = np.exp(-ratio)
    positive = dt > 0.0
    g = np.where(positive, -np.expm1(-ratio) / np.where(positive, ratio, 1.0), 1.0)
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
    def tau_s(self) -> float:
        """Return the first-order lag in s, 0 without one (read once: used on every sample)."""
        return self._param('first_order_lag', 'tau_s')

    @property
    def output_offset_s(self) -> float:
        return self._param('time_offset', 'offset_s')

    @property
    def output_offset_ns(self) -> int:
        return int(round(self.output_offset_s * 1e9))

    def extension_values(self) -> dict[str, dict[str, float]]:
        """Return {extension: {parameter: value}} in application order."""
        return {name: get_extension(name).mapping(k)
                for name, k in zip(self.extensions, self.values)}

    def memoryless(self, omega_l, omega_r, t_s) -> np.ndarray:
        """Return x: the base twist after the twist-stage extensions (..., 3)."""
        omega_l = np.asarray(omega_l, dtype=float)
        omega_r = np.asarray(omega_r, dtype=float)
        twist = self.base.twist(omega_l, omega_r)
        for name, k in zip(self.extensions, self.values):
            twist = get_extension(name).apply(k, twist, omega_l, omega_r, t_s)
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

    def scalar_memoryless(self, omega_l: float, omega_r: float,
                          t_s: float) -> tuple[float, float, float]:
        """:meth:`memoryless` for one sample on plain floats (equal to it bit for bit)."""
        chain = self._scalar_chain
        if chain is None:  # an extension without a float form (the sparse correction)
            vx, vy, w = np.asarray(self.memoryless(omega_l, omega_r, t_s), dtype=float).tolist()
            return vx, vy, w
        vx, vy, w = self.base.scalar_twist(omega_l, omega_r)
        for function, k in chain:
            vx, vy, w = function(k, vx, vy, w, omega_l, omega_r, t_s)
        return vx, vy, w

    def begin(self, state: AugmentedState | None, t_ns: int, omega_l: float, omega_r: float,
              restart: bool) -> tuple[AugmentedState, tuple[float, float, float]]:
        """Take a new sample; return the new state and the body twist published now."""
        t0 = t_ns if state is None else state.t0_ns
        x = self.scalar_memoryless(float(omega_l), float(omega_r), (t_ns - t0) * 1e-9)
        if state is None or restart or not self.tau_s > 0.0:
            y = x
        else:
            y = state.y
        return AugmentedState(t0, x, y), y

    def advance(self, state: AugmentedState, dt_s: float
                ) -> tuple[AugmentedState, tuple[float, float, float]]:
        """Return the state after holding for dt_s and the mean twist over that interval.

        :func:`lag_factors` and :func:`lag_response`'s sample loop on plain floats.
        """
        tau = self.tau_s
        if not tau > 0.0:
            return state, state.x
        ratio = dt_s / tau
        d = float(np.exp(-ratio))
        g = -float(np.expm1(-ratio)) / ratio if dt_s > 0.0 else 1.0
        (x0, x1, x2), (y0, y1, y2) = state.x, state.y
        diff0, diff1, diff2 = y0 - x0, y1 - x1, y2 - x2
        return (AugmentedState(state.t0_ns, state.x,
                               (x0 + diff0 * d, x1 + diff1 * d, x2 + diff2 * d)),
                (x0 + diff0 * g, x1 + diff1 * g, x2 + diff2 * g))

    # ---------------------------------------------------------------- batch form
    def intervals(self, t_ns: np.ndarray, omega_l: np.ndarray, omega_r: np.ndarray,
                  dt_s: np.ndarray, restart: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Batch form over (D, L): (published twists, mean twists over each interval)."""
        t_ns = np.asarray(t_ns, dtype=np.int64)
        t_s = (t_ns - t_ns[:, :1]) * 1e-9
        x = np.asarray(self.memoryless(omega_l, omega_r, t_s), dtype=float)
        tau = self.tau_s
        if not tau > 0.0:
            return x, x
        return lag_response(x, np.asarray(dt_s, dtype=float), np.asarray(restart, bool), tau)


def lag_response(x: np.ndarray, dt_s: np.ndarray, restart: np.ndarray,
                 tau_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Run the first-order response over (D, L) rows: (published twists, mean twists).

    Rows sampled at a constant period without restart go through scipy's lfilter (the same
    recursion, to rounding); the others through the sample loop the streaming form runs.
    """
    d, g = lag_factors(dt_s, tau_s)
    held = np.empty_like(x)
    length = x.shape[1]
    steady = np.array([length > 2 and not restart[r].any()
                       and np.all(dt_s[r, :-1] == dt_s[r, 0]) and dt_s[r, 0] > 0
                       for r in range(x.shape[0])], dtype=bool)
    for r in np.nonzero(steady)[0]:
        decay = float(d[r, 0])
        held[r] = lfilter([0.0, 1.0 - decay], [1.0, -decay], x[r], axis=0,
                          zi=x[r, :1].copy())[0]
    rows = np.nonzero(~steady)[0]
    if rows.size:
        xs, ds, rs = x[rows], d[rows], restart[rows]
        y = xs[:, 0].copy()
        for i in range(length):
            held[rows, i] = y
            if i + 1 < length:
                x_i = xs[:, i]
                y = np.where(rs[:, i + 1, None], xs[:, i + 1], x_i + (y - x_i) * ds[:, i, None])
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


def _pad_drives(drives: Sequence[Drive]
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    width = max(max((len(d.wheels) for d in drives), default=1), 1)
    count = len(drives)
    t = np.zeros((count, width), dtype=np.int64)
    wl = np.zeros((count, width))
    wr = np.zeros((count, width))
    sizes = np.zeros(count, dtype=int)
    for i, drive in enumerate(drives):
        n = len(drive.wheels)
        sizes[i] = n
        if n == 0:
            continue
        t[i, :n] = drive.wheels.t_ns
        t[i, n:] = drive.wheels.t_ns[-1]
        wl[i, :n] = drive.wheels.omega_l
        wr[i, :n] = drive.wheels.omega_r
        wl[i, n:] = drive.wheels.omega_l[-1]
        wr[i, n:] = drive.wheels.omega_r[-1]
    return t, wl, wr, sizes


class SegmentPredictor:
    """Predict segment end poses with any (stateful) source, over whole drives.

    The source runs over every drive (its state evolves along the drive as in the node); each
    segment then integrates the mean twists of the wheel samples held over its window
    [t_a - offset, t_b - offset] from its ground-truth start pose. With a plain base model and no
    offset this is exactly what :func:`skidkin_ros.core.fitting.predict_end_poses` computes.
    """

    def __init__(self, drives: Sequence[Drive], segments: SegmentSet,
                 max_dt_s: float = 0.5) -> None:
        self.drives = list(drives)
        self.segments = segments
        self.t_ns, self.omega_l, self.omega_r, self.sizes = _pad_drives(self.drives)
        dt = np.zeros(self.t_ns.shape)
        dt[:, :-1] = np.diff(self.t_ns, axis=1) * 1e-9
        self.restart = np.zeros(self.t_ns.shape, dtype=bool)
        self.restart[:, 1:] = dt[:, :-1] > max_dt_s
        dt[dt > max_dt_s] = 0.0
        self.dt_s = dt
        self.step_s = np.diff(self.t_ns, axis=1) * 1e-9  # between stamps, gaps included
        self._plans: dict[int, dict[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.segments)

    def plan(self, offset_ns: int) -> dict[str, np.ndarray]:
        """Return how each segment's window [t_a - offset, t_b - offset] meets the samples.

        Flat sample indices (into the padded (D, L) arrays) and durations, one per segment:
        ``first``/``first_s``: the sample held from the window start to the first stamp inside
        it (to the window end when none is inside); ``a``/``b``: the first and last stamps inside
        (equal when none is: no whole interval); ``last_s``: how long sample ``b`` is held from
        its stamp to the window end (0 s when no stamp is inside).
        """
        cached = self._plans.get(offset_ns)
        if cached is not None:
            return cached
        width = self.t_ns.shape[1]
        seg = self.segments
        count = len(seg)
        plan = {key: np.zeros(count, dtype=np.int64) for key in ('first', 'a', 'b')}
        plan.update(first_s=np.zeros(count), last_s=np.zeros(count))
        for d in np.unique(seg.drive):
            rows = np.nonzero(seg.drive == d)[0]
            stamps = self.t_ns[d, :self.sizes[d]]
            top = stamps.size - 1
            s_a = seg.t_a_ns[rows].astype(np.int64) - offset_ns
            s_b = seg.t_b_ns[rows].astype(np.int64) - offset_ns
            lo = np.searchsorted(stamps, s_a, side='right')
            hi = np.maximum(np.searchsorted(stamps, s_b, side='left'), lo)
            inner = hi > lo
            a = np.clip(lo, 0, top)
            b = np.where(inner, hi - 1, a)
            plan['first'][rows] = np.clip(lo - 1, 0, top) + d * width
            plan['a'][rows] = a + d * width
            plan['b'][rows] = b + d * width
            plan['first_s'][rows] = np.where(inner, stamps[a] - s_a, s_b - s_a) * 1e-9
            plan['last_s'][rows] = np.where(inner, s_b - stamps[b], 0) * 1e-9
        if len(self._plans) > 64:
            self._plans.clear()
        self._plans[offset_ns] = plan
        return plan

    def cumulative_poses(self, mean: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the dead-reckoned pose at every stamp of every drive, flat (D * L,) each.

        Each drive starts at the origin and integrates every sample interval with its mean
        twist, for the time between the stamps (as a segment does, gaps included).
        """
        count, width = self.t_ns.shape
        if width < 2:
            zeros = np.zeros(count * width)
            return zeros, zeros.copy(), zeros.copy()
        rows = mean.reshape(count, width, 3)
        x, y, yaw = rollout_columns(np.ascontiguousarray(rows[:, :-1, 0]),
                                    np.ascontiguousarray(rows[:, :-1, 1]),
                                    np.ascontiguousarray(rows[:, :-1, 2]), self.step_s,
                                    np.zeros((count, 3)))
        return x.ravel(), y.ravel(), yaw.ravel()

    def mean_twists(self, source: Any) -> np.ndarray:
        """Return the mean twist over every sample interval of every drive, flat (D * L, 3)."""
        if is_stateful(source):
            _, mean = source.intervals(self.t_ns, self.omega_l, self.omega_r, self.dt_s,
                                       self.restart)
        else:
            mean = np.asarray(source.twist(self.omega_l, self.omega_r), dtype=float)
        return mean.reshape(-1, 3)

    def predict_ends(self, source: Any, keep: np.ndarray | None = None) -> np.ndarray:
        """Return the predicted end pose (S, 3) of every segment (or of ``keep`` indices).

        The end pose is the start pose composed with three moves: the partial interval up to
        the first stamp inside the window, the dead-reckoned motion between the first and last
        stamps inside it (from the drive's cumulative poses: one rollout per drive, shared by
        every segment), and the partial interval to the window end. The same steps as
        integrating each window on its own, in O(samples + segments).
        """
        plan = self.plan(int(getattr(source, 'output_offset_ns', 0)))
        start = self.segments.start
        if keep is not None:
            plan = {key: value[keep] for key, value in plan.items()}
            start = start[keep]
        mean = self.mean_twists(source)
        cx, cy, cyaw = self.cumulative_poses(mean)
        a, b = plan['a'], plan['b']
        dx, dy = cx[b] - cx[a], cy[b] - cy[a]
        cos_a, sin_a = np.cos(cyaw[a]), np.sin(cyaw[a])
        moves = (body_increment(*mean[plan['first']].T, plan['first_s']),
                 (cos_a * dx + sin_a * dy, cos_a * dy - sin_a * dx, cyaw[b] - cyaw[a]),
                 body_increment(*mean[b].T, plan['last_s']))
        x, y, yaw = start[:, 0], start[:, 1], start[:, 2]
        for move in moves:
            x, y, yaw = compose(x, y, yaw, *move)
        return np.stack([x, y, yaw], axis=-1)

    def errors(self, source: Any, keep: np.ndarray | None = None) -> np.ndarray:
        """Return the end-pose error of every segment in its start frame (true - predicted)."""
        start, end = self.segments.start, self.segments.end
        if keep is not None:
            start, end = start[keep], end[keep]
        with np.errstate(all='ignore'):
            predicted = self.predict_ends(source, keep)
        return segment_frame_error(start, end, predicted)


def relative_errors(errors: np.ndarray, path_m: np.ndarray,
                    min_path_m: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Return eps_t (m/m) and eps_theta (deg/m) of the segments at least min_path_m long."""
    scored = path_m >= min_path_m
    path = path_m[scored]
    return (np.hypot(errors[scored, 0], errors[scored, 1]) / path,
            np.degrees(np.abs(errors[scored, 2])) / path)
