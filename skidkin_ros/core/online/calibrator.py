"""Online calibration: the active model's parameters learned from a reference, while driving.

The odometer (:class:`~skidkin_ros.core.odometry.odometer.Odometer`) hands every integrated wheel
step and every reference pose to an :class:`OnlineCalibrator`; when the parameters change, the
odometer integrates with the new ones and publishes their uncertainty. The node and
``skidkin predict --reference`` run the same object in the same order, so they agree bit for
bit. The recipe, for one reference pose:

1. **Judge it on arrival** (:meth:`OnlineCalibrator.reference`): a NaN, a zero stamp, a stamp
   not after the last accepted one, a frame other than the configured one, or a pose closer
   than 1/``max_rate`` to the last one is refused, counted by cause
   (:class:`~skidkin_ros.core.odometry.reference.ReferenceStatus`). It is turned into the base
   frame's pose (``mount_*``) and its stamp into wheel time (``time_offset``), then waits until
   the wheel steps cover it.
2. **Judge it against the wheels**: a gap longer than ``max_gap`` or a wheel gap restarts the
   chain; a pose that disagrees with the wheels' travel by ``max_jump`` (plus half the travel)
   is a jump (three in a row: the reference relocalised, the chain restarts there); a pose that
   does not move while the wheels travel ``stall`` is stalled. None of these ever reaches the
   odometry: it goes on with what it has learned.
3. **Cut segments by the calibrator's rule** (:meth:`SegmentOptions.ends`: ``horizon`` m of
   reference path or ``horizon_rad`` of turning, the calibrator's h_t), non-overlapping, each
   made of the wheel steps it spans (split at its ends, as
   :func:`~skidkin_ros.core.calibration.segments.cut_segments` splits them).
4. **Residual, Jacobian and weight by the calibrator's functions**:
   :func:`~skidkin_ros.core.calibration.fitting.segment_errors` (end-pose error in the start
   frame), :func:`~skidkin_ros.core.calibration.noise_fit.parameter_sensitivity` (its derivative
   with respect to the parameters) and the covariance of the model's noise over that segment
   (:func:`~skidkin_ros.core.calibration.noise_fit.segment_covariances`, the weighting of the
   iterated fit) plus the reference's own noise at both ends.
5. **Change of ground** (CUSUM of the segment's NEES against its predictive covariance): when it
   passes ``cusum_threshold``, a remembered ground that explains the segment is taken back,
   else a new ground starts from the current parameters with the broad prior (state
   ``adapting``: for ``adapt_distance`` m the memory is ``adapt_memory`` instead of ``memory``).
   On every accepted reference pose, the last ``switch_window`` m are scored under every
   remembered ground: one that is better by ``switch_margin`` becomes the active one (two grounds
   that alternate every few metres are recognised, not averaged).
6. **Update only what the segment observes** (information-form recursive least squares with
   forgetting toward the prior): the information Lambda fades by exp(-path / memory) toward the
   prior's; the segment's information H = S^T Sigma^-1 S is split into eigen-directions (in
   units of each parameter's typical magnitude) and only those that gain at least
   ``min_information`` are updated (driving straight says nothing about the ICR: its direction
   keeps its value and its uncertainty grows back toward the prior). One Gauss-Newton step in that
   subspace; values kept inside their ranges and the model's constraints.

Memory and CPU are bounded: the wheel steps since the oldest pose still needed (a segment's
start, the window's start) and at most ``MAX_STEPS`` of them; a segment costs 2p + 2 rollouts of
its steps (vectorized), a window one rollout per remembered ground.
"""

from __future__ import annotations

import bisect
import collections
from dataclasses import dataclass, field
import math
from typing import Mapping

import numpy as np

from skidkin_ros.core.calibration.fitting import parameter_scales, segment_errors
from skidkin_ros.core.calibration.noise_fit import (mahalanobis, parameter_sensitivity,
                                                    segment_covariances, segment_motion)
from skidkin_ros.core.calibration.segments import HorizonOptions, SegmentOptions, SegmentSet
from skidkin_ros.core.kinematics.models import BoundModel, KinematicModel
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.noise import NoiseModel
from skidkin_ros.core.odometry.reference import base_pose, OnlineParams, ReferenceStatus
from skidkin_ros.core.odometry.uncertainty import ParameterUncertainty
from skidkin_ros.core.timeunits import NS_PER_S
from skidkin_ros.errors import ParameterError

__all__ = ['OnlineCalibrator', 'Ground', 'MAX_STEPS', 'STATES']

# Wheel steps kept at most (a minute at 1 kHz): a segment longer than this is abandoned.
MAX_STEPS = 60_000
# Jumps in a row that mean the reference relocalised (its chain restarts there).
JUMP_CONFIRM = 3
# Wheel steps shorter than this are merged (time-weighted mean speeds) inside learning segments.
BLOCK_S = 0.05
# Reference poses kept for the window (beyond: the oldest go).
MAX_REFERENCES = 4096
# A ground whose segment NEES is below this (chi2, 3 dof, 99 %) explains the segment.
CHI2_99_3DOF = 11.34
STATES = ('holding', 'learning', 'adapting')


@dataclass
class Ground:
    """One ground: its parameters, prior, window of segments and information.

    Information matrices are in units of each parameter's typical magnitude. ``anchor`` and
    ``prior`` are the prior (where the ground started, how sure of it); ``window`` the recent
    segments with their weight matrices and the travel at which they were learned.
    """

    ident: int
    k: np.ndarray
    prior: np.ndarray
    anchor: np.ndarray = None
    info: np.ndarray = None
    window: list = field(default_factory=list)
    learned_m: float = 0.0
    segments: int = 0
    last_used: int = 0

    def __post_init__(self) -> None:
        if self.anchor is None:
            self.anchor = self.k.copy()
        if self.info is None:
            self.info = self.prior.copy()


class _Ref:
    """One accepted reference pose, base frame, in wheel time, with the cumulative path."""

    __slots__ = ('t_ns', 'x', 'y', 'yaw', 'path_m')

    def __init__(self, t_ns: int, x: float, y: float, yaw: float, path_m: float) -> None:
        self.t_ns, self.x, self.y, self.yaw, self.path_m = t_ns, x, y, yaw, path_m


class OnlineCalibrator:
    """Learns the parameters of ``model`` from a reference (see the module docstring).

    ``counters`` (shared with the odometer) counts every reference pose by
    :class:`ReferenceStatus` and every learning event ('online_segments', 'online_change',
    'online_switch', 'online_inconsistent', ...). ``warn(cause, message)`` hears the faults.
    """

    def __init__(self, model: KinematicModel, values: Mapping[str, float], geometry: Geometry,
                 noise: NoiseModel | None, params: OnlineParams, interval: str,
                 prior_covariance: np.ndarray | None = None,
                 counters: collections.Counter[str] | None = None, warn=None) -> None:
        if not model.params:
            raise ParameterError(f'online calibration: model {model.name!r} has no parameter '
                                 'to learn; choose a calibrated model')
        self.model = model
        self.geometry = geometry
        self.noise = noise or NoiseModel(1e-3, 1e-3, 1e-4, 1e-3)
        self.params = params
        self.counters: collections.Counter[str] = (collections.Counter() if counters is None
                                                   else counters)
        self._warn = warn or (lambda *a, **k: None)
        self.scale = parameter_scales(model, geometry)
        self.options = SegmentOptions(
            horizon_m=params.horizon, horizon_rad=params.horizon_rad,
            min_motion_m=HorizonOptions.min_motion_m,
            min_rotation_rad=HorizonOptions.min_rotation_rad, interval=interval)
        self.k0 = model.vector(dict(values), geometry)
        self.prior_info = np.eye(self.k0.size) / params.prior_sigma ** 2
        info = self.prior_info.copy()
        if prior_covariance is not None and np.any(prior_covariance):
            scaled = np.asarray(prior_covariance, float) / np.outer(self.scale, self.scale)
            info = info + np.linalg.pinv(scaled)
        self.grounds = [Ground(0, self.k0.copy(), info)]
        self.active = self.grounds[0]
        self._next_ident = 1
        self._error = np.zeros((3, 3))
        self.version = 0              # grows when the parameters in force change
        self.travel_m = 0.0           # reference path accepted, in all
        self._adapt_until_m = -1.0
        self.cusum = 0.0
        self.last_nees = math.nan
        self._lo, self._hi = self._bounds()
        self._offset_ns = params.time_offset_ns
        self._min_period_ns = NS_PER_S / params.max_rate
        self._restart_buffers()
        self._last_arrival_ns: int | None = None

    # ------------------------------------------------------------------ state
    def _restart_buffers(self) -> None:
        # Wheel steps (t0, t1] with the speeds integrated and the model's twist; chain ids
        # tell contiguous steps apart from steps after a gap.
        self._t1: list[int] = []
        # per step: (t0, left speed, right speed, model v_x, model yaw rate, chain id)
        self._rows: list[tuple[int, float, float, float, float, int]] = []
        self._chain_id = 0
        self._last_t1: int | None = None
        self._pending: collections.deque[tuple[int, float, float, float]] = collections.deque()
        self._refs: collections.deque[_Ref] = collections.deque()
        self._seg_start: _Ref | None = None
        self._seg_version = self.version
        self._jumps = 0
        self._stall_m = 0.0
        self._last_seen: tuple[int, float, float, float] | None = None
        self._recognised_m = -math.inf
        self._last_accepted_wheel_ns: int | None = None

    def restart(self) -> None:
        """Forget the buffered wheel steps and reference poses (a reset); keep the grounds."""
        self._restart_buffers()

    @property
    def k(self) -> np.ndarray:
        return self.active.k

    @property
    def values(self) -> dict[str, float]:
        """Return the parameters in force, by name."""
        return self.model.mapping(self.active.k)

    @property
    def covariance(self) -> np.ndarray:
        """Return the covariance of the parameters in force (p, p), in their units."""
        return np.linalg.inv(self.active.info) * np.outer(self.scale, self.scale)

    def bound_model(self) -> BoundModel:
        return BoundModel(self.model, self.geometry, self.active.k.copy())

    def uncertainty(self) -> ParameterUncertainty | None:
        return ParameterUncertainty.of_model(self.model, self.active.k, self.geometry,
                                             self.covariance)

    def state(self, wheel_now_ns: int | None = None) -> str:
        """Return 'holding' (no usable reference lately), 'adapting' or 'learning'."""
        now = self._last_t1 if wheel_now_ns is None else wheel_now_ns
        last = self._last_accepted_wheel_ns
        if last is None or now is None or now - last > self.params.max_gap * NS_PER_S:
            return 'holding'
        return 'adapting' if self.travel_m < self._adapt_until_m else 'learning'

    def summary(self) -> dict[str, float | str]:
        """Return what /diagnostics reports: state, parameters, their sigmas, grounds."""
        out: dict[str, float | str] = {'state': self.state(), 'ground': float(self.active.ident),
                                       'grounds': float(len(self.grounds)),
                                       'learned_m': self.active.learned_m,
                                       'travel_m': self.travel_m, 'cusum': self.cusum,
                                       'last_nees': self.last_nees}
        sigma = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        for name, value, sd in zip(self.model.param_names, self.active.k, sigma):
            out[f'{name}'] = float(value)
            out[f'{name}.sigma'] = float(sd)
        return out

    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = [], []
        for spec, scale in zip(self.model.params, self.scale):
            lo.append(spec.lower + (1e-6 * scale if spec.lower_open else 0.0))
            hi.append(spec.upper - (1e-6 * scale if spec.upper_open else 0.0))
        return np.array(lo), np.array(hi)

    # ------------------------------------------------------------------ wheel steps
    def wheel_break(self, t_ns: int) -> None:
        """Start a new chain of steps at a wheel sample held only (the first, after a gap)."""
        self._chain_id += 1
        self._last_t1 = t_ns

    def wheel_step(self, t1_ns: int, wheels: tuple[float, float] | None,
                   twist: tuple[float, float, float]) -> bool:
        """Take one integrated step ending at t1_ns; True when the parameters changed."""
        t0 = self._last_t1
        self._last_t1 = t1_ns
        if t0 is None or wheels is None:
            self._chain_id += 1
            return False
        self._t1.append(t1_ns)
        self._rows.append((t0, wheels[0], wheels[1], twist[0], twist[2], self._chain_id))
        if len(self._t1) > MAX_STEPS:
            self.counters['online_segment_too_long'] += 1
            self._seg_start = None
            self._refs.clear()
            self._trim(t1_ns)
        before = self.version
        pending = self._pending
        while pending and pending[0][0] <= t1_ns:
            self._judge(*pending.popleft())
        if not pending and not len(self._t1) & 255:
            self._trim_old()
        return self.version != before

    def _trim_old(self) -> None:
        keep = self._seg_start.t_ns if self._seg_start is not None else self._last_t1
        if self._refs:
            keep = min(keep, self._refs[0].t_ns)
        if keep is not None:
            self._trim(keep)

    def _trim(self, keep_ns: int) -> None:
        """Drop the wheel steps that end before keep_ns (amortised: in halves)."""
        n = bisect.bisect_left(self._t1, keep_ns)
        if n > 256 and (n > len(self._t1) // 2 or len(self._t1) > MAX_STEPS):
            del self._t1[:n]
            del self._rows[:n]

    # ------------------------------------------------------------------ reference poses
    def reference(self, t_ns: int, x: float, y: float, yaw: float, frame_id: str = '',
                  child_frame_id: str = '') -> tuple[ReferenceStatus, bool]:
        """Take a reference pose of the reference frame, stamped t_ns (reference clock).

        Returns (status on arrival, whether the parameters changed). A pose accepted on arrival
        may still be judged a gap, a jump or a stall once the wheels cover it (counted then).
        """
        status = self._arrival(t_ns, x, y, yaw, frame_id, child_frame_id)
        if status is not ReferenceStatus.ACCEPTED:
            self._count(status, f'reference pose {status.value.removeprefix("reference_")}'
                        f' (stamp {t_ns * 1e-9:.3f} s): not used; the odometry goes on with '
                        'the parameters learned so far')
            return status, False
        self._last_arrival_ns = t_ns
        bx, by, byaw = base_pose(x, y, yaw, self.params)
        item = (t_ns - self._offset_ns, bx, by, byaw)
        before = self.version
        if self._last_t1 is not None and item[0] <= self._last_t1 and not self._pending:
            self._judge(*item)
        else:
            self._pending.append(item)
            if len(self._pending) > MAX_REFERENCES:
                self._count(ReferenceStatus.UNCOVERED, 'reference poses wait for wheel data '
                            'that does not come: the oldest is dropped')
                self._pending.popleft()
        return status, self.version != before

    def _arrival(self, t_ns: int, x: float, y: float, yaw: float, frame_id: str,
                 child_frame_id: str) -> ReferenceStatus:
        params = self.params
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(yaw)):
            return ReferenceStatus.NON_FINITE
        if t_ns <= 0:
            return ReferenceStatus.BAD_STAMP
        if ((params.reference_frame_id and frame_id != params.reference_frame_id)
                or (params.reference_child_frame_id
                    and child_frame_id != params.reference_child_frame_id)):
            return ReferenceStatus.FRAME
        last = self._last_arrival_ns
        if last is not None:
            if t_ns <= last:
                return ReferenceStatus.OLDER
            if t_ns - last < self._min_period_ns:
                return ReferenceStatus.RATE_LIMITED
        if abs(x) > 1e9 or abs(y) > 1e9:
            return ReferenceStatus.NON_FINITE
        return ReferenceStatus.ACCEPTED

    def _count(self, status: ReferenceStatus, message: str) -> None:
        self.counters[status.value] += 1
        self._warn(status.value, message)

    def _wheel_motion(self, t_a: int, t_b: int) -> tuple[float, float] | None:
        """Return the wheel travel (m) and rotation (rad) over (t_a, t_b]; None: not covered."""
        t1 = self._t1
        i0 = bisect.bisect_right(t1, t_a)
        i1 = bisect.bisect_left(t1, t_b)
        rows = self._rows
        if i1 >= len(t1) or i0 > i1 or rows[i0][0] > t_a or rows[i0][5] != rows[i1][5]:
            return None
        dist = rot = 0.0
        for i in range(i0, i1 + 1):
            t0, _, _, speed, yaw_rate, _ = rows[i]
            dt = (min(t1[i], t_b) - max(t0, t_a)) * 1e-9
            dist += abs(speed) * dt
            rot += yaw_rate * dt
        return dist, rot

    def _judge(self, t_ns: int, x: float, y: float, yaw: float) -> None:
        """Judge a reference pose the wheels now cover; use it if it is good."""
        if not self._t1 or t_ns <= self._rows[0][0]:
            self._count(ReferenceStatus.UNCOVERED, 'reference pose before the first wheel '
                        'step kept (time_offset wrong, or wheel data missing)')
            return
        seen, self._last_seen = self._last_seen, (t_ns, x, y, yaw)
        if seen is not None and seen[1:] == (x, y, yaw):
            moved = self._wheel_motion(seen[0], t_ns)
            self._stall_m += 0.0 if moved is None else moved[0]
            if self._stall_m > self.params.stall:
                self._count(ReferenceStatus.STALL, f'reference frozen while the wheels '
                            f'travelled {self._stall_m:.2f} m: not used, segment dropped')
                self._seg_start = None
                return
        else:
            self._stall_m = 0.0
        last = self._refs[-1] if self._refs else None
        if last is None:
            self._start_chain(t_ns, x, y, yaw)
            return
        if t_ns - last.t_ns > self.params.max_gap * NS_PER_S:
            self._count(ReferenceStatus.GAP, f'reference gap of {(t_ns - last.t_ns) * 1e-9:.2f} '
                        f's (max_gap {self.params.max_gap:g} s): segment dropped, restarting')
            self._start_chain(t_ns, x, y, yaw)
            return
        motion = self._wheel_motion(last.t_ns, t_ns)
        if motion is None:
            self._count(ReferenceStatus.WHEEL_GAP, 'the wheel data has a gap since the last '
                        'reference pose: segment dropped, restarting')
            self._start_chain(t_ns, x, y, yaw)
            return
        yaw = last.yaw + _wrap(yaw - last.yaw)
        dist = float(np.hypot(x - last.x, y - last.y))
        wheel_dist, wheel_rot = motion
        params = self.params
        if (abs(dist - wheel_dist) > params.max_jump + 0.5 * wheel_dist
                or abs((yaw - last.yaw) - wheel_rot) > params.max_jump_rad
                + 0.5 * abs(wheel_rot)):
            self._jumps += 1
            self._count(ReferenceStatus.JUMP, f'reference moved {dist:.2f} m / '
                        f'{yaw - last.yaw:+.2f} rad where the wheels say {wheel_dist:.2f} m / '
                        f'{wheel_rot:+.2f} rad: refused')
            if self._jumps >= JUMP_CONFIRM:
                self._start_chain(t_ns, x, y, yaw)
            return
        self._jumps = 0
        ref = _Ref(t_ns, x, y, yaw, last.path_m + dist)
        self._accept(ref)

    def _start_chain(self, t_ns: int, x: float, y: float, yaw: float) -> None:
        self._refs.clear()
        self._jumps = 0
        ref = _Ref(t_ns, x, y, yaw, 0.0)
        self._refs.append(ref)
        self._seg_start = ref
        self._seg_version = self.version
        self._last_accepted_wheel_ns = t_ns
        self.counters[ReferenceStatus.ACCEPTED.value] += 1

    def _accept(self, ref: _Ref) -> None:
        refs = self._refs
        refs.append(ref)
        self.counters[ReferenceStatus.ACCEPTED.value] += 1
        self.travel_m += ref.path_m - refs[-2].path_m
        self._last_accepted_wheel_ns = ref.t_ns
        if len(refs) > MAX_REFERENCES:
            refs.popleft()
        start = self._seg_start
        if start is None:
            self._seg_start = ref
            self._seg_version = self.version
        elif self.options.ends(start.path_m, ref.path_m, ref.yaw - start.yaw,
                               ref.t_ns - start.t_ns):
            self._learn(start, ref)
            self._seg_start = ref
            self._seg_version = self.version
        if len(self.grounds) > 1 and not (
                0.0 <= ref.path_m - self._recognised_m < 0.5 * self.params.switch_window):
            self._recognised_m = ref.path_m
            self._recognise(ref)
        # the window needs only the last switch_window metres
        window = self.params.switch_window
        while len(refs) > 2 and refs[1].path_m <= ref.path_m - window and (
                self._seg_start is None or refs[1].t_ns <= self._seg_start.t_ns):
            refs.popleft()

    # ------------------------------------------------------------------ segments
    def _segment(self, a: _Ref, b: _Ref) -> SegmentSet | None:
        """Return the segment a -> b as the calibrator's SegmentSet (one row), or None."""
        t1, rows = self._t1, self._rows
        i0 = bisect.bisect_right(t1, a.t_ns)
        i1 = bisect.bisect_left(t1, b.t_ns)
        if i1 >= len(t1) or i0 > i1 or rows[i0][0] > a.t_ns or rows[i0][5] != rows[i1][5]:
            return None
        stamps = np.array(t1[i0:i1 + 1], dtype=np.int64)
        chunk = rows[i0:i1 + 1]
        starts = np.array([row[0] for row in chunk], dtype=np.int64)
        table = np.array([row[1:3] for row in chunk])
        dt_s = (np.minimum(stamps, b.t_ns) - np.maximum(starts, a.t_ns)) * 1e-9
        if dt_s.max() > self.options.max_gap_s:
            return None
        left, right, dt_s = _blocks(table[:, 0], table[:, 1], dt_s)
        return SegmentSet(
            drive=np.zeros(1, dtype=int), t_a_ns=np.array([a.t_ns], np.int64),
            t_b_ns=np.array([b.t_ns], np.int64), start=np.array([[a.x, a.y, a.yaw]]),
            end=np.array([[b.x, b.y, b.yaw]]), omega_l=left[None], omega_r=right[None],
            dt_s=dt_s[None], path_m=np.array([b.path_m - a.path_m]))

    def _reference_cov(self) -> np.ndarray:
        sx, syaw = self.params.sigma_xy, self.params.sigma_yaw
        return np.diag([2 * sx * sx, 2 * sx * sx, 2 * syaw * syaw])

    def _score(self, ground: Ground, seg: SegmentSet, motion_cov: np.ndarray,
               with_parameters: bool) -> tuple[np.ndarray, np.ndarray | None, float]:
        """Return (residual, sensitivity or None, NEES) of a segment under one ground."""
        e = segment_errors(self.model, ground.k, self.geometry, seg)[0]
        cov = motion_cov + self._reference_cov()
        sens = None
        if with_parameters:
            sens = parameter_sensitivity(self.model.name, self.model.mapping(ground.k),
                                         self.geometry, seg)[0] * self.scale
            cov = cov + sens @ np.linalg.inv(ground.info) @ sens.T
        return e, sens, float(mahalanobis(cov[None], e[None])[0])

    def _motion_cov(self, seg: SegmentSet) -> np.ndarray:
        motion = segment_motion(self.model.name, self.model.mapping(self.active.k),
                                self.geometry, seg)
        return segment_covariances(self.noise, motion)[0]

    def _learn(self, a: _Ref, b: _Ref) -> None:
        """One learning segment: gates, change detection, the update (module docstring)."""
        if self.options.too_still(b.path_m - a.path_m, b.yaw - a.yaw):
            self.counters['online_still'] += 1
            return
        seg = self._segment(a, b)
        if seg is None:
            self.counters['online_wheel_gap'] += 1
            return
        if self._seg_version != self.version:
            # the parameters switched inside this segment: it may straddle two grounds
            self.counters['online_straddles'] += 1
            return
        motion_cov = self._motion_cov(seg)
        ground = self.active
        # the residuals of the window and the new segment at once (one set of rollouts)
        errors, sens = self._residuals(ground, [item[0] for item in ground.window] + [seg])
        e = errors[-1]
        predictive = (motion_cov + self._reference_cov()
                      + sens[-1] @ np.linalg.inv(ground.info) @ sens[-1].T)
        nees = float(mahalanobis(predictive[None], e[None])[0])
        path, rot = b.path_m - a.path_m, b.yaw - a.yaw
        params = self.params
        if (math.hypot(e[0], e[1]) > params.max_jump + 0.5 * path
                or abs(e[2]) > params.max_jump_rad + 0.5 * abs(rot)):
            self.counters['online_inconsistent'] += 1
            self._warn('online_inconsistent', f'a {path:.2f} m segment disagrees with the '
                       f'wheels by {math.hypot(e[0], e[1]):.2f} m / {e[2]:+.2f} rad: beyond any '
                       'ground (max_jump); not learned')
            return
        self.last_nees = nees
        self.cusum = max(0.0, self.cusum + nees - params.cusum_drift)
        if self.cusum > params.cusum_threshold:
            self._note_error(seg, e)
            self._change(seg, motion_cov)
            if self.active is not ground:   # a new ground starts from ground.k: same rows
                errors, sens = ((errors[-1:], sens[-1:]) if not self.active.window
                                else (None, None))
        self._update(seg, motion_cov + self._reference_cov(), path, errors, sens)

    def _residuals(self, ground: Ground, segments: list[SegmentSet]
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Return the residuals (N, 3) and their sensitivities (N, 3, p; scaled units)."""
        batch = _stack(segments)
        errors = segment_errors(self.model, ground.k, self.geometry, batch)
        sens = parameter_sensitivity(self.model.name, self.model.mapping(ground.k),
                                     self.geometry, batch) * self.scale
        return errors, sens

    def _change(self, seg: SegmentSet, motion_cov: np.ndarray) -> None:
        """Take back a known ground, or start a new one (the CUSUM passed its threshold)."""
        self.cusum = 0.0
        best, best_nees = None, CHI2_99_3DOF
        for ground in self.grounds:
            if ground is self.active:
                continue
            nees = self._score(ground, seg, motion_cov, True)[2]
            if nees < best_nees:
                best, best_nees = ground, nees
        if best is not None:
            self._activate(best, 'online_switch')
            return
        ground = Ground(self._next_ident, self.active.k.copy(), self.prior_info.copy())
        self._next_ident += 1
        if len(self.grounds) >= int(self.params.max_grounds):
            oldest = min((g for g in self.grounds if g is not self.active),
                         key=lambda g: g.last_used, default=None)
            if oldest is not None:
                self.grounds.remove(oldest)
            else:
                self.grounds.remove(self.active)
        self.grounds.append(ground)
        self._adapt_until_m = self.travel_m + self.params.adapt_distance
        self._activate(ground, 'online_change')
        self._warn('online_change', f'change of ground detected: learning ground {ground.ident} '
                   f'from the current parameters ({len(self.grounds)} grounds known)')

    def _note_error(self, seg: SegmentSet, residual: np.ndarray) -> None:
        """Keep the error the old ground made on the segment that revealed the change.

        The odometry carried that error already, with a covariance that did not know the ground
        had changed: the odometer adds it (world frame, e e^T) to the published covariance once
        (:meth:`take_error`), so the covariance stays honest across a change.
        """
        c, s = math.cos(float(seg.start[0, 2])), math.sin(float(seg.start[0, 2]))
        world = np.array([c * residual[0] - s * residual[1], s * residual[0] + c * residual[1],
                          residual[2]])
        self._error = self._error + np.outer(world, world)

    def take_error(self) -> np.ndarray | None:
        """Return the error noted since the last call (3 x 3, world frame), or None."""
        error, self._error = self._error, np.zeros((3, 3))
        return error if error.any() else None

    def _activate(self, ground: Ground, cause: str) -> None:
        self.counters[cause] += 1
        self.active = ground
        ground.last_used = self.counters['online_segments'] + self.counters[cause]
        self.version += 1

    def _update(self, seg: SegmentSet, cov: np.ndarray, path_m: float,
                errors: np.ndarray | None = None, sens: np.ndarray | None = None) -> None:
        """Add the segment to the window; one Gauss-Newton step in the observable directions.

        The window's segments fade by exp(-path / memory) at every new segment (forgetting:
        faster while adapting, and what faded then stays faded) and are
        relinearised at the current parameters (no early linearisation stays baked in, as in a
        plain recursive filter); the prior (the ground's start, its information) keeps the
        unobserved directions where they were and bounds their uncertainty. ``errors`` and
        ``sens``: the residuals of the window and the segment at the current parameters, when
        known (None: computed here).
        """
        ground = self.active
        params = self.params
        memory = params.adapt_memory if self.travel_m < self._adapt_until_m else params.memory
        fade = math.exp(-path_m / memory)
        for item in ground.window:
            item[2] *= fade
        items = ground.window + [[seg, np.linalg.inv(cov), 1.0]]
        first = max(len(items) - int(params.window), 0)
        keep = [i for i in range(first, len(items)) if items[i][2] > 1e-3]
        ground.window = [items[i] for i in keep]
        self.counters['online_segments'] += 1
        ground.segments += 1
        ground.learned_m += path_m
        ground.last_used = self.counters['online_segments']
        if errors is None or len(errors) != len(items):
            e, sens = self._residuals(ground, [item[0] for item in ground.window])
        else:
            e, sens = errors[keep], sens[keep]
        weights = np.array([item[2] for item in ground.window])
        inverse = np.stack([item[1] for item in ground.window]) * weights[:, None, None]
        data = np.einsum('nip,nij,njq->pq', sens, inverse, sens)
        data = 0.5 * (data + data.T)
        u_offset = (ground.k - ground.anchor) / self.scale
        gradient = np.einsum('nip,nij,nj->p', sens, inverse, e) - ground.prior @ u_offset
        ground.info = data + ground.prior
        values, vectors = np.linalg.eigh(data)
        observed = values >= max(params.min_information, 1e-9 * max(values.max(), 0.0))
        if not observed.any():
            self.counters['online_unobservable'] += 1
            return
        basis = vectors[:, observed]
        step = basis @ np.linalg.solve(basis.T @ ground.info @ basis, basis.T @ gradient)
        k = np.clip(ground.k + step * self.scale, self._lo, self._hi)
        try:
            self.model.check_constraints(k)
        except ParameterError:
            self.counters['online_update_refused'] += 1
            return
        ground.k = k
        self.version += 1

    def _recognise(self, ref: _Ref) -> None:
        """Score the last switch_window metres under every ground; take a clearly better one."""
        refs = self._refs
        window = self.params.switch_window
        if ref.path_m - refs[0].path_m < window:
            return
        start = refs[0]
        for item in refs:
            if item.path_m > ref.path_m - window:
                break
            start = item
        seg = self._segment(start, ref)
        if seg is None:
            return
        path = ref.path_m - start.path_m
        rot = abs(ref.yaw - start.yaw)
        # a diagonal weight from the noise rates (the grounds are compared on the same one)
        var_x, var_y, var_yaw = self.noise.step_variances(path, rot)
        motion_cov = np.diag([var_x + self.noise.var_x_const, var_y + self.noise.var_y_const,
                              var_yaw + self.noise.var_yaw_const]) + 1e-9 * np.eye(3)
        scores = [(self._score(g, seg, motion_cov, False), g) for g in self.grounds]
        active, residual = next((s[2], s[0]) for s, g in scores if g is self.active)
        best, ground = min(((s[2], g) for s, g in scores), key=lambda item: item[0])
        if ground is not self.active and active - best > self.params.switch_margin:
            self._note_error(seg, residual)
            self._activate(ground, 'online_switch')
            self.cusum = 0.0


def _blocks(left: np.ndarray, right: np.ndarray, dt_s: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge wheel steps into blocks of about BLOCK_S (speeds averaged over time).

    A fast wheel stream (1 kHz) would make every rollout of a segment 50 times longer than at
    20 Hz for no information: the twist is linear in the speeds over a few milliseconds. Steps
    already longer than half a block are kept as they are.
    """
    if dt_s.size < 2 or dt_s.sum() >= 0.5 * BLOCK_S * dt_s.size:
        return left, right, dt_s
    start = np.concatenate([[0.0], np.cumsum(dt_s)[:-1]])
    ids = np.floor(start / BLOCK_S).astype(np.int64)
    first = np.flatnonzero(np.diff(ids, prepend=-1))
    dt_b = np.add.reduceat(dt_s, first)
    return (np.add.reduceat(left * dt_s, first) / dt_b,
            np.add.reduceat(right * dt_s, first) / dt_b, dt_b)


def _stack(segments: list[SegmentSet]) -> SegmentSet:
    """Return one-row segment sets as one set, padded with dt = 0 to the longest."""
    if len(segments) == 1:
        return segments[0]
    width = max(seg.dt_s.shape[1] for seg in segments)

    def pad(name: str) -> np.ndarray:
        out = np.zeros((len(segments), width))
        for i, seg in enumerate(segments):
            row = getattr(seg, name)[0]
            out[i, :row.size] = row
        return out
    return SegmentSet(
        drive=np.zeros(len(segments), dtype=int),
        t_a_ns=np.concatenate([seg.t_a_ns for seg in segments]),
        t_b_ns=np.concatenate([seg.t_b_ns for seg in segments]),
        start=np.concatenate([seg.start for seg in segments]),
        end=np.concatenate([seg.end for seg in segments]),
        omega_l=pad('omega_l'), omega_r=pad('omega_r'), dt_s=pad('dt_s'),
        path_m=np.concatenate([seg.path_m for seg in segments]))


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi
