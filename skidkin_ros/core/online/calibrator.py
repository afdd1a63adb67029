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
   that alternate every few metres are recognised, not averaged). The segment in progress is
   scored every 0.5 m (a change is declared on it), the ground taken learns from the located
   change on, and from its growing segment while adapting (``adapt.py``).
6. **Update only what the segment observes** (information-form recursive least squares with
   forgetting toward the prior): the information Lambda fades by exp(-path / memory) toward the
   prior's; the segment's information H = S^T Sigma^-1 S is split into eigen-directions (in
   units of each parameter's typical magnitude) and only those that gain at least
   ``min_information`` are updated (driving straight says nothing about the ICR: its direction
   keeps its value and its uncertainty grows back toward the prior). One Gauss-Newton step in that
   subspace; values kept inside their ranges and the model's constraints.

7. **The published noise** is the file's times the calibrator's coverage factor on the
   odometry's own errors over the last segments (``noise.py``).

Memory and CPU are bounded: the wheel steps since the oldest pose still needed (a segment's
start, the window's start) and at most ``MAX_STEPS`` of them; a segment costs 2p + 2 rollouts of
its steps (vectorized), a window one rollout per remembered ground.
"""

from __future__ import annotations

import bisect
import collections
import math
from typing import Mapping

import numpy as np

from skidkin_ros.core.calibration.fitting import parameter_scales
from skidkin_ros.core.calibration.noise_fit import mahalanobis
from skidkin_ros.core.calibration.segments import HorizonOptions, SegmentOptions, SegmentSet
from skidkin_ros.core.kinematics.models import BoundModel, KinematicModel
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.noise import NoiseModel
from skidkin_ros.core.odometry.reference import OnlineParams
from skidkin_ros.core.odometry.uncertainty import ParameterUncertainty
from skidkin_ros.core.online.adapt import ChangeLearner
from skidkin_ros.core.online.delay import DelayCheck
from skidkin_ros.core.online.gates import (_Ref, JUMP_CONFIRM, MAX_REFERENCES,  # noqa: F401
                                           ReferenceGates)
from skidkin_ros.core.online.grounds import CHI2_99_3DOF, Ground, GroundBank  # noqa: F401
from skidkin_ros.core.online.gyrochoice import GyroChoice
from skidkin_ros.core.online.heading import HeadingRule
from skidkin_ros.core.online.holding import HoldingBlend
from skidkin_ros.core.online.noise import NoiseLearner
from skidkin_ros.core.online.position import PositionLearner
from skidkin_ros.core.online.refnoise import RefNoiseLearner
from skidkin_ros.core.online.steps import WheelSteps
from skidkin_ros.core.online.window import WindowSolver
from skidkin_ros.core.timeunits import NS_PER_S, s_to_ns
from skidkin_ros.errors import ParameterError

__all__ = ['OnlineCalibrator', 'Ground', 'MAX_STEPS', 'STATES']

# Wheel steps kept at most (a minute at 1 kHz): a segment longer than this is abandoned.
MAX_STEPS = 60_000
# Steps between two checks of that bound (and trims of the steps no longer needed).
CHECK_STEPS = 256
# No reference pose pending: no wheel step is due for one.
NEVER_NS = 1 << 62
# Wheel steps shorter than this are merged (time-weighted mean speeds) inside learning segments.
BLOCK_S = 0.05
STATES = ('holding', 'learning', 'adapting')
# The reference gates (gates.py), the ground bank and its change detector (grounds.py) and the
# window re-solve (window.py) are mixins of OnlineCalibrator; their names are re-exported here.


class OnlineCalibrator(HoldingBlend, GyroChoice, HeadingRule, PositionLearner, ChangeLearner,
                       NoiseLearner, RefNoiseLearner, ReferenceGates, GroundBank, WindowSolver):
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
            # the prior is a floor of the file's information, not added to it: a covariance
            # ~/save_calibration wrote holds it already (added again at every restart, it
            # shrank as 1/sqrt(n + 1) with no data: 0.5 -> 0.18 in a week of restarts; C290)
            values, vectors = np.linalg.eigh(np.linalg.pinv(scaled))
            info = (vectors * np.maximum(values, self.prior_info[0, 0])) @ vectors.T
        self.grounds = [Ground(0, self.k0.copy(), info)]
        self._start_info = info.copy()   # a corrected delay restarts learning here (delay.py)
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
        self._delay = DelayCheck(params.time_offset, params.delay_tolerance,
                                 geometry.track_width, self.counters, self._warn,
                                 params.delay_learn > 0.5, model.rows(self.k0, geometry))
        self._restart_buffers()

    # ------------------------------------------------------------------ state
    def _restart_buffers(self) -> None:
        # Wheel steps (t0, t1] with the speeds integrated and the model's twist (steps.py);
        # chain ids tell contiguous steps apart from steps after a gap.
        self._steps = WheelSteps()
        self._t1 = self._steps.t1        # the lists wheel_step appends to (the same objects)
        self._rows = self._steps.rows
        self._chain_id = 0
        self._travel = self._turn = 0.0   # running sums of |v_x| dt and omega dt (steps.py)
        self._last_t1: int | None = None
        self._pending: collections.deque[tuple[int, float, float, float]] = collections.deque()
        # wheel_step has work beyond appending when a step reaches _due_ns (the oldest pending
        # reference pose) or after _countdown more steps (the bound on the steps kept)
        self._due_ns = NEVER_NS
        self._countdown = CHECK_STEPS
        self._refs: collections.deque[_Ref] = collections.deque()
        self._seg_start: _Ref | None = None
        self._seg_version = self.version
        self._jumps = 0
        self._stall_m = 0.0
        self._last_seen: tuple[int, float, float, float] | None = None
        self._recognised_m = -math.inf
        self._last_accepted_wheel_ns: int | None = None
        # the last stamp accepted on arrival; forgotten with the buffers, or a clock that
        # jumped back (a bag replayed in a loop) would refuse every later pose as older
        self._last_arrival_ns: int | None = None
        self._delay.forget()

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
        return BoundModel(self.model, self.geometry, self.in_force()[0].copy())

    def uncertainty(self) -> ParameterUncertainty | None:
        k, covariance = self.in_force()   # the active ground's, or the blend while holding
        return ParameterUncertainty.of_model(self.model, k, self.geometry, covariance)

    def state(self, wheel_now_ns: int | None = None) -> str:
        """Return 'holding', 'adapting' or 'learning'.

        Holding: no usable reference for online.max_gap, or the gyro refused one that lately.
        """
        now = self._last_t1 if wheel_now_ns is None else wheel_now_ns
        last = self._last_accepted_wheel_ns
        if last is None or now is None or now - last > self.params.max_gap * NS_PER_S:
            return 'holding'
        if now - self.gyro_refused_ns <= self.params.max_gap * NS_PER_S:
            return 'holding'   # the gyro refused the reference lately: learning paused
        if self._delay.pausing:
            return 'holding'   # the reference's delay is not time_offset (delay.py)
        return 'adapting' if self.travel_m < self._adapt_until_m else 'learning'

    def summary(self) -> dict[str, float | str]:
        """Return what /diagnostics reports: state, parameters, their sigmas, grounds."""
        out: dict[str, float | str] = {'state': self.state(), 'ground': float(self.active.ident),
                                       'grounds': float(len(self.grounds)),
                                       'learned_m': self.active.learned_m,
                                       'travel_m': self.travel_m, 'cusum': self.cusum,
                                       'last_nees': self.last_nees,
                                       'last_refusal': self.last_refusal or 'none',
                                       'noise_scale': self.noise_scale,
                                       'reference_heading': self.heading_state(),
                                       'hold_weight': self.hold_weight()}
        out['reference_sigma_xy'], out['reference_sigma_yaw'] = self.reference_sigmas()
        out.update(self._delay.summary())
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
        """Take one integrated step ending at t1_ns; True when the parameters changed.

        Per wheel sample this appends the step and compares two numbers; the work (judging a
        reference pose, cutting and learning a segment, trimming) happens when a pending
        reference pose is covered, or every CHECK_STEPS steps.
        """
        t0 = self._last_t1
        self._last_t1 = t1_ns
        if t0 is None or wheels is None:
            self._chain_id += 1
            return False
        dt_s = (t1_ns - t0) * 1e-9
        v_x, yaw_rate = twist[0], twist[2]
        travel = self._travel = self._travel + abs(v_x) * dt_s
        turn = self._turn = self._turn + yaw_rate * dt_s
        self._t1.append(t1_ns)
        self._rows.append((t0, wheels[0], wheels[1], v_x, yaw_rate, self._chain_id, travel, turn))
        self._countdown -= 1
        if t1_ns < self._due_ns and self._countdown > 0:
            return False
        return self._wheel_work(t1_ns)

    def _wheel_work(self, t1_ns: int) -> bool:
        """Judge the reference poses the steps now cover; bound the steps kept."""
        if self._countdown <= 0:
            self._countdown = CHECK_STEPS
            if len(self._t1) > MAX_STEPS:
                self.counters['online_segment_too_long'] += 1
                self._seg_start = None
                self._refs.clear()
                self._trim(t1_ns)
        before = self.version
        pending = self._pending
        while pending and pending[0][0] <= t1_ns:
            self._judge(*pending.popleft())
        self._due_ns = pending[0][0] if pending else NEVER_NS
        if not pending:
            self._trim_old()
        self._hold_check(t1_ns)
        return self.version != before

    def _judge(self, t_ns: int, x: float, y: float, yaw: float) -> None:
        """Judge a covered reference pose (gates.py); the delay check sees it (delay.py)."""
        super()._judge(t_ns, x, y, yaw)
        delay = self._delay
        delay.seen(self._refs, self._t1, self._rows)
        if delay.correction is not None:   # a measured delay taken in force: stamps move
            self._offset_ns = s_to_ns(delay.correction)
            delay.correction = None
            self._pending.clear()          # converted with the old offset (the same deque)
            self._restart_buffers()
            # what was learned under the wrong stamps is dropped: the file's parameters again
            self.grounds = [Ground(0, self.k0.copy(), self._start_info.copy())]
            self.active = self.grounds[0]
            self._next_ident = 1
            self.cusum = 0.0
            self._adapt_until_m = -1.0
            self._blend = None
            self.version += 1

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
            self._delay.wheels(self._t1, self._rows)   # the delay check reads them first
            self._steps.drop(n)

    # ------------------------------------------------------------------ segments
    @staticmethod
    def _merge_blocks(left: np.ndarray, right: np.ndarray, dt_s: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return :func:`_blocks` of the steps (for the mixins: position.py)."""
        return _blocks(left, right, dt_s)

    def _segment(self, a: _Ref, b: _Ref) -> SegmentSet | None:
        """Return the segment a -> b as the calibrator's SegmentSet (one row), or None."""
        steps = self._steps.speeds(a.t_ns, b.t_ns)
        if steps is None:
            return None
        left, right, dt_s = steps
        if dt_s.max() > self.options.max_gap_s:
            return None
        left, right, dt_s = _blocks(left, right, dt_s)
        return SegmentSet(
            drive=np.zeros(1, dtype=int), t_a_ns=np.array([a.t_ns], np.int64),
            t_b_ns=np.array([b.t_ns], np.int64), start=np.array([[a.x, a.y, a.yaw]]),
            end=np.array([[b.x, b.y, b.yaw]]), omega_l=left[None], omega_r=right[None],
            dt_s=dt_s[None], path_m=np.array([b.path_m - a.path_m]))

    def _learn(self, a: _Ref, b: _Ref) -> None:
        """One learning segment: gates, change detection, the update (module docstring)."""
        if self._delay.pausing:   # the reference's delay is not time_offset (delay.py)
            self.counters['online_reference_delay'] += 1
            return
        if self.options.too_still(b.path_m - a.path_m, b.yaw - a.yaw):
            self.counters['online_still'] += 1
            return
        wheels = self._wheel_motion(a.t_ns, b.t_ns)
        if wheels is not None and self.options.too_still(*wheels):
            # no parameters make still wheels move the robot (the twist is J(k) times the
            # speeds): nothing to learn, and no change of ground to declare
            self.counters['online_wheels_still'] += 1
            self._warn('online_wheels_still', f'the reference moved {b.path_m - a.path_m:.2f} m '
                       f'/ {b.yaw - a.yaw:+.2f} rad while the wheels did not (robot carried, or '
                       'sliding with its wheels locked): not learned')
            return
        if self._heading_constant_over(a.t_ns, a.yaw, b.yaw):   # heading.py
            self.counters['online_heading_constant'] += 1
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
        if params.disagrees(math.hypot(e[0], e[1]), path, e[2], rot):
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
            if self.active is not ground:   # learn from the located change on (adapt.py)
                seg = self._after_change(a, b, ground)
                if seg is None:
                    return
                path = float(seg.path_m[0])
                motion_cov = self._motion_cov(seg)
                errors = sens = None
        self._update(seg, motion_cov + self._reference_cov(), path, errors, sens)


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
