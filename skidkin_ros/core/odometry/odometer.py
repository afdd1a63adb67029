"""The odometer: what odom_node does with every wheel sample, in plain numbers, without ROS.

diff_drive_controller keeps its ``Odometry`` class apart from the controller; so does skidkin. The
node (``skidkin_ros.node``) turns messages into numbers, reads its clock and publishes; everything
between is here, and ``skidkin predict`` runs the very same steps over recorded samples, so the
node and the offline prediction agree by construction. For one sample:

1. Stamp it (:meth:`Odometer.joint_sample`): a zero header stamp is refused, or replaced by the
   receive time when ``zero_stamp_uses_receive_time``; a negative stamp is refused, and so is a
   stamp more than ``future_tolerance`` ahead of the node clock. Two Float64 wheel topics carry
   no stamp: their values are paired within ``pair_tolerance`` and stamped with the receive time
   (:meth:`Odometer.wheel_sample`, :class:`~skidkin_ros.core.odometry.wheels.WheelPairer`).
   A stamp more than ``max_stamp_step_back`` behind the last accepted one is refused, unless
   ``STEP_BACK_CONFIRM`` samples in a row (increasing, each within ``max_dt`` of the previous)
   say the input clock itself stepped back (a driver restarted): then the odometry is reset to
   the origin, as for a sim-time jump, and goes on from the new clock. ~/reset and
   ~/set_pose (:meth:`Odometer.reset`) change the pose and its covariance only: the last stamp
   and held speeds stay, so the next sample integrates the whole interval since the previous one
   (diff_drive_controller keeps its wheel baseline the same way) and a stale or tiny stamp right
   after a reset is refused; :meth:`Odometer.clock_changed` (a new clock) forgets them.
2. Integrate it (:meth:`Odometer.step`): the streaming integrator checks the speeds and the
   stamp (duplicate, older, gap), advances the pose, and the covariance is propagated over the
   integrated step. Every outcome is counted by cause; rejections are reported to ``warn``.
3. Decide what to publish (:meth:`Odometer.update`): nothing for a duplicate stamp (the held
   speeds are updated; a second message with the same stamp would confuse an EKF), nothing
   closer than 1/``max_rate`` to the last output, nothing non-finite; otherwise an
   :class:`Estimate` stamped with the sample stamp plus the model's time offset (an augmented
   model's pose integrated to t is the pose at t + offset).

Each kind of input enters through its own method and ends in :meth:`Odometer.update`, so a new
input (encoder positions differenced into speeds, an IMU's yaw rate) or a new stamp check joins
the same pipeline without touching the node.

The limits of a pose set from outside live in :mod:`~skidkin_ros.core.odometry.pose_limits`, the
offline result (:class:`Prediction`) and its feeds in :mod:`~skidkin_ros.core.odometry.prediction`;
both are re-exported here. This module stays over 500 lines for one reason: :class:`Odometer` is
one state machine (stamp rules, pairing, gyro wait, integration, covariance, publish decision)
whose steps share its state on every sample; split across modules, each would reach into it.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, replace
import math
from typing import Any, Callable, Container, Mapping, NamedTuple, Protocol, Sequence

import numpy as np

from skidkin_ros.core.drive import ImuSamples, PoseTrack, WheelSamples
from skidkin_ros.core.kinematics.specs import DEFAULT_GEOMETRY
from skidkin_ros.core.odometry.config import node_default, OdometryConfig
from skidkin_ros.core.odometry.controller import ControllerGeometry, NonFiniteTwistError
from skidkin_ros.core.odometry.gyro import GyroAid, GyroParams, GyroStatus, STEP_BACK_CONFIRM
from skidkin_ros.core.odometry.integrator import (IntegratorLimits, SampleStatus, step_scalar,
                                                  StepResult, StreamingIntegrator, TwistSource)
from skidkin_ros.core.odometry.interval import DEFAULT_INTERVAL
from skidkin_ros.core.odometry.noise import (FALLBACK_POSE_DIAGONAL, FALLBACK_TWIST_DIAGONAL,
                                             moving_time)
from skidkin_ros.core.odometry.pose_limits import (check_covariance, check_pose, POSE_LIMIT_M,
                                                   VARIANCE_LIMIT, YAW_LIMIT_RAD,
                                                   YAW_RESOLUTION_RAD)
from skidkin_ros.core.odometry.prediction import _GyroFeed, _ReferenceFeed, Prediction
from skidkin_ros.core.odometry.propagation import (PoseCovariancePropagator,
                                                   TWIST_VARIANCE_FLOOR)
from skidkin_ros.core.odometry.residual_uncertainty import ResidualUncertainty
from skidkin_ros.core.odometry.wheels import Pairing, WheelPairer, WheelSignal
from skidkin_ros.core.timeunits import NS_PER_S

__all__ = ['SampleRules', 'Estimate', 'Odometer', 'Prediction', 'predict_wheels',
           'check_pose', 'check_covariance', 'POSE_LIMIT_M', 'YAW_LIMIT_RAD',
           'YAW_RESOLUTION_RAD', 'VARIANCE_LIMIT',
           'STEP_BACK_CONFIRM']

# Wheel samples that may wait for the gyro at once (beyond: the oldest goes on without it).
MAX_PENDING = 1000
Triple = tuple[float, float, float]
Warn = Callable[..., None]  # warn(cause, message, error=False)


class Learner(Protocol):
    """What the odometer needs of an online calibrator (skidkin_ros.core.online)."""

    def wheel_step(self, t1_ns: int, wheels: tuple[float, float] | None,
                   twist: Triple) -> bool: ...

    def wheel_break(self, t_ns: int) -> None: ...

    def reference(self, t_ns: int, x: float, y: float, yaw: float, frame_id: str,
                  child_frame_id: str, yaw_variance: float) -> tuple[Any, bool]: ...

    def restart(self) -> None: ...

    def bound_model(self) -> TwistSource: ...

    def uncertainty(self) -> Any: ...

    def take_error(self) -> Any: ...

    def published_noise(self) -> Any: ...


@dataclass(frozen=True)
class SampleRules:
    """How samples are stamped and how often odometry is published (node parameters)."""

    zero_stamp_uses_receive_time: bool = False
    future_tolerance_s: float = node_default('future_tolerance')
    pair_tolerance_s: float = node_default('pair_tolerance')
    max_rate_hz: float = node_default('max_rate')
    max_stamp_step_back_s: float = node_default('max_stamp_step_back')

    @classmethod
    def from_config(cls, config: OdometryConfig) -> 'SampleRules':
        return cls(config['zero_stamp_uses_receive_time'], config['future_tolerance'],
                   config['pair_tolerance'], config['max_rate'], config['max_stamp_step_back'])


class Estimate(NamedTuple):
    """One odometry output: stamp (ns), pose (x, y, yaw), body twist and their covariances.

    The covariances are row-major 6 x 6 (x, y, z, roll, pitch, yaw), 36 floats each, as
    nav_msgs/Odometry carries them. (A named tuple: one is made per published sample.)
    """

    t_ns: int
    pose: Triple
    twist: Triple
    pose_covariance: list[float]
    twist_covariance: list[float]


_new_estimate = tuple.__new__


def _ignore(*args: object, **kwargs: object) -> None:
    """Ignore an event (the listener of offline prediction)."""


class Odometer:
    """Wheel samples in, odometry estimates out (see the module docstring for the recipe).

    ``counters`` (a Counter, shared with the caller if given) counts every sample by outcome
    (``SampleStatus`` values, and 'zero_stamp', 'future_stamp', 'unpaired', 'rate_limited',
    'non_finite_output', 'published'). ``warn(cause, message, error=False)`` hears about every
    rejected or doubtful sample; ``fresh()`` is called for every accepted one.
    """

    def __init__(self, source: TwistSource, limits: IntegratorLimits | None = None,
                 rules: SampleRules | None = None,
                 covariance: PoseCovariancePropagator | None = None, *,
                 counters: collections.Counter[str] | None = None, warn: Warn | None = None,
                 fresh: Callable[[], None] | None = None, imu: GyroParams | None = None,
                 wheel_radius_m: float = DEFAULT_GEOMETRY.wheel_radius,
                 interval: str = DEFAULT_INTERVAL, wheel_signal: str = 'velocity',
                 note: Callable[[str], None] | None = None,
                 controller: ControllerGeometry | None = None) -> None:
        self.integrator = StreamingIntegrator(source, limits, interval)
        # The drive controller's geometry, for input odometry (twist_sample); None otherwise.
        self.controller = controller
        self.signal = WheelSignal(wheel_signal, self.integrator.limits.max_wheel_speed_rad_s)
        self._note = note or _ignore
        self.covariance = covariance or PoseCovariancePropagator(
            None, FALLBACK_POSE_DIAGONAL, FALLBACK_TWIST_DIAGONAL)
        self.counters: collections.Counter[str] = (collections.Counter() if counters is None
                                                   else counters)
        self._warn = warn or _ignore
        self._fresh = fresh or _ignore
        self.pairer = WheelPairer(0.0)
        self.set_rules(rules or SampleRules())
        self.period_s = 0.0
        self.last_published_t_ns: int | None = None
        # The last accepted input stamp, kept across reset() (see the module docstring).
        self.last_input_t_ns: int | None = None
        self._step_back_run: list[int] = []
        # Wheel samples waiting for the gyro samples that cover them: (t_ns, l, r, arrival_ns).
        self._pending: collections.deque[tuple[int, float, float, int]] = collections.deque()
        self.gyro: GyroAid | None = None
        self.set_imu(imu or GyroParams(), wheel_radius_m)
        # An online calibrator (skidkin_ros.core.online) learning the model's parameters from a
        # reference, attached by its maker; None: the parameters are the file's (the default).
        self.learner: Learner | None = None

    @classmethod
    def from_config(cls, config: OdometryConfig, model: str | None = None, *,
                    counters: collections.Counter[str] | None = None, warn: Warn | None = None,
                    fresh: Callable[[], None] | None = None,
                    note: Callable[[str], None] | None = None) -> 'Odometer':
        """Return the odometer a configuration describes (``model`` replaces its model).

        ``note(message)`` hears which wheel signal is in use when that changes.
        """
        return cls(config.bound_model(model), config.limits, SampleRules.from_config(config),
                   _propagator(config), counters=counters, warn=warn, fresh=fresh,
                   imu=config.imu, wheel_radius_m=config.geometry.wheel_radius,
                   interval=config['interval'], wheel_signal=config['wheel_signal'], note=note,
                   controller=_controller(config))

    # ------------------------------------------------------------------ state
    @property
    def pose(self) -> np.ndarray:
        """Return the current (x, y, yaw), yaw unwrapped (a new array)."""
        return self.integrator.pose

    @property
    def output_offset_ns(self) -> int:
        """Return the offset (ns) added to a sample stamp for what is published."""
        return self.integrator.output_offset_ns

    def set_rules(self, rules: SampleRules) -> None:
        """Use new stamp, pairing and rate rules from the next sample on."""
        self.rules = rules
        self._future_ns = rules.future_tolerance_s * NS_PER_S
        self._min_period_ns = NS_PER_S / rules.max_rate_hz if rules.max_rate_hz > 0.0 else 0.0
        self.pairer.tolerance_ns = rules.pair_tolerance_s * NS_PER_S
        self._step_back_ns = rules.max_stamp_step_back_s * NS_PER_S
        gyro = getattr(self, 'gyro', None)
        if gyro is not None:
            gyro.buffer.max_step_back_ns = self._step_back_ns

    def configure(self, config: OdometryConfig) -> None:
        """Switch to a validated configuration; the pose and its covariance are kept."""
        self.integrator.set_source(config.bound_model(), config['interval'])
        self.integrator.limits = config.limits
        if (config['wheel_signal'], config['max_wheel_speed']) != (
                self.signal.mode, self.signal.max_speed_rad_s):
            self.signal = WheelSignal(config['wheel_signal'], config['max_wheel_speed'])
        covariance = _propagator(config)
        covariance.reset(float(self.pose[2]))
        covariance.cov = self.covariance.cov.copy()
        self.covariance = covariance
        self.set_rules(SampleRules.from_config(config))
        self.set_imu(config.imu, config.geometry.wheel_radius)
        self.controller = _controller(config)

    def set_imu(self, params: GyroParams, wheel_radius_m: float) -> None:
        """Use the gyro as ``params`` say (mode off: not at all).

        Unchanged parameters keep the gyro history and the learned gain and bias; changed ones
        start them afresh (from the calibrated model).
        """
        gyro = self.gyro
        if (gyro is not None and gyro.params == params
                and gyro.wheel_radius_m == float(wheel_radius_m)):
            return
        self.gyro = None if params.mode == 'off' else GyroAid(params, wheel_radius_m)
        if self.gyro is not None:
            self.gyro.buffer.max_step_back_ns = self._step_back_ns
        self.integrator.aid = self.gyro
        if self.gyro is None:
            self._pending.clear()

    def reset(self, pose: Sequence[float] = (0.0, 0.0, 0.0),
              covariance: np.ndarray | None = None) -> None:
        """Set the pose (default: the origin) and its covariance; the integration goes on.

        Only the pose and its covariance change (~/reset, ~/set_pose): the last stamp, the held
        speeds, the wheel positions, a wheel value waiting for its partner and the gyro are kept,
        so the next sample integrates the whole interval since the last one, as
        diff_drive_controller keeps its wheel baseline across a reset. The covariance restarts
        from (almost) zero, plus ``covariance`` (a 3 x 3 (x, y, yaw) block) when given. A pose or
        covariance the odometry cannot hold (:func:`check_pose`, :func:`check_covariance`)
        raises ValueError and changes nothing. Only a new clock forgets the baseline
        (:meth:`clock_changed`).
        """
        pose = check_pose(pose)
        block = None if covariance is None else check_covariance(covariance)
        self.integrator.restart_pose(pose)
        self._reset_covariance(pose[2])
        if block is not None:
            self.covariance.cov = self.covariance.cov + block
        self.last_published_t_ns = None

    def _reset_covariance(self, yaw_rad: float) -> None:
        """Restart the pose covariance from (almost) zero, and with it the gyro bias's share."""
        self.covariance.reset(yaw_rad)
        if self.gyro is not None:
            self.gyro.bias_yaw_sd = 0.0

    def _restart(self, pose: Sequence[float] = (0.0, 0.0, 0.0)) -> None:
        """Start afresh at ``pose``: held speeds, last stamp and waiting values forgotten."""
        pose = check_pose(pose)
        self.integrator.reset(pose)
        self._reset_covariance(pose[2])
        self.period_s = 0.0
        self.last_published_t_ns = None
        self.pairer.clear()
        self.signal.clear()
        self._step_back_run.clear()
        self._pending.clear()
        if self.learner is not None:
            self.learner.restart()

    def clock_changed(self) -> None:
        """Restart at the origin and forget the last input stamp (the clock itself jumped)."""
        self._restart()
        self.last_input_t_ns = None
        if self.gyro is not None:
            self.gyro.buffer.clear()

    # ------------------------------------------------------------------ online calibration
    def attach_learner(self, learner: 'Learner | None') -> None:
        """Learn the parameters online with ``learner`` (None: the file's, fixed) from now on."""
        self.learner = learner
        if learner is not None:
            self.apply_learned()

    def apply_learned(self) -> None:
        """Integrate with the learner's parameters and publish their uncertainty."""
        learner = self.learner
        uncertainty = learner.uncertainty()
        if not np.all(np.isfinite(learner.k)) or (
                uncertainty is not None and not np.all(np.isfinite(uncertainty.covariance))):
            # the odometry never becomes non-finite because of what it learns: keep the last
            self.counters['online_nonfinite'] += 1
            return
        self.integrator.set_source(learner.bound_model())
        if self.covariance.calibrated:
            self.covariance.set_parameters(uncertainty)
            self.covariance.noise = learner.published_noise()
            error = learner.take_error()
            if error is not None:  # what the old ground's parameters got wrong, carried
                self.covariance.cov = self.covariance.cov + error

    def reference_sample(self, t_ns: int, x: float, y: float, yaw: float,
                         frame_id: str = '', child_frame_id: str = '',
                         yaw_variance: float = math.nan) -> str:
        """Take a reference pose (online calibration); return its status's counter name.

        ``yaw_variance``: the pose covariance's yaw entry (rad^2; NaN: none given). Without a
        learner the pose is counted 'reference_ignored'. The odometry is never held up or
        changed by the pose itself: only the parameters it teaches change.
        """
        learner = self.learner
        if learner is None:
            self.counters['reference_ignored'] += 1
            return 'reference_ignored'
        status, changed = learner.reference(t_ns, x, y, yaw, frame_id, child_frame_id,
                                            yaw_variance)
        if changed:
            self.apply_learned()
        return status.value

    # ------------------------------------------------------------------ inputs
    def joint_sample(self, t_ns: int, omega_l: float, omega_r: float, now_ns: int,
                     positions: tuple[Sequence[float], Sequence[float]] | None = None,
                     what: str = 'JointState') -> Estimate | None:
        """Take a stamped sample (a JointState's) received at ``now_ns`` on the node clock.

        ``positions``: the left and right wheel joints' positions (rad), None when the message
        has none; ``wheel_signal`` says which of them and the speeds is integrated
        (:class:`~skidkin_ros.core.odometry.wheels.WheelSignal`). ``what`` names the message
        type in the warnings.
        """
        if t_ns == 0:
            if not self.rules.zero_stamp_uses_receive_time:
                self._reject('zero_stamp', f'{what} header.stamp is zero; sample rejected '
                             '(set zero_stamp_uses_receive_time to use the receive time '
                             'instead)')
                return None
            t_ns = now_ns
        elif t_ns < 0:
            self._reject('negative_stamp', f'{what} stamp is negative ({t_ns / NS_PER_S:.3f} '
                         's); sample rejected: ROS time starts at 0, check the driver clock')
            return None
        ahead_ns = t_ns - now_ns
        if ahead_ns > self._future_ns:
            self._reject('future_stamp',
                         f'{what} stamp is {ahead_ns / NS_PER_S:.3f} s ahead of the node '
                         f'clock (future_tolerance {self.rules.future_tolerance_s:g} s); sample '
                         'rejected: check the clocks of the driver and this machine')
            return None
        taken = self.signal.take(t_ns, omega_l, omega_r, positions)
        if taken.switched:
            plural = 'positions' if taken.switched == 'position' else 'velocities'
            self._note(f'wheel signal: integrating the wheel {plural} (wheel_signal '
                       f'{self.signal.mode})')
        if taken.warning is not None:
            self._reject(*taken.warning)
        if taken.speeds is None:
            self._reject(taken.cause, taken.detail)
            return None
        return self.update(t_ns, *taken.speeds, now_ns, check_jump=not taken.by_position)

    def twist_sample(self, t_ns: int, v_m_s: float, w_rad_s: float, now_ns: int
                     ) -> Estimate | None:
        """Take a drive controller's odometry twist (v m/s, w rad/s) stamped ``t_ns``.

        The wheel speeds the controller saw are recovered with its configured geometry
        (:meth:`~skidkin_ros.core.odometry.controller.ControllerGeometry.wheel_speeds`, the one
        rule the bag reader uses too), then the sample goes the JointState way. A NaN or
        infinite twist is refused (``non_finite_twist``).
        """
        if self.controller is None:
            self._reject('no_controller_geometry', 'Odometry wheel input without the '
                         "controller's geometry (input odometry sets controller.*); dropped")
            return None
        try:
            omega_l, omega_r = self.controller.wheel_speeds(v_m_s, w_rad_s)
        except NonFiniteTwistError as err:
            self._reject('non_finite_twist', f'Odometry twist rejected: {err}; the controller '
                         'published a broken twist, nothing integrated for it')
            return None
        return self.joint_sample(t_ns, omega_l, omega_r, now_ns, what='Odometry')

    def wheel_sample(self, side: str, omega_rad_s: float, now_ns: int) -> Estimate | None:
        """Take one side's unstamped speed (a Float64 topic's) received at ``now_ns``."""
        other = 'right' if side == 'left' else 'left'
        seen_ns = self.pairer.last_seen_ns[other]
        outcome, sample = self.pairer.offer(side, now_ns, float(omega_rad_s))
        if sample is not None:
            return self.update(*sample)
        if outcome is Pairing.UNPAIRED:
            age = ('never received' if seen_ns is None
                   else f'last sample {(now_ns - seen_ns) / NS_PER_S:.3f} s ago')
            self._reject('unpaired',
                         f'{other} wheel speed is stale ({age}); not integrating until both '
                         'sides arrive within pair_tolerance '
                         f'{self.rules.pair_tolerance_s:g} s')
        return None

    def imu_sample(self, t_ns: int, yaw_rate: float, now_ns: int) -> list[Estimate]:
        """Take a gyro yaw rate (rad/s, base frame z) stamped ``t_ns``, received at ``now_ns``.

        Ignored (counted) with mode off. A zero, negative or future stamp is refused; NaN, inf,
        saturated, older and duplicate samples are counted by the buffer and never used. Returns
        the estimates of wheel samples that were waiting for it (see :meth:`update`).
        """
        gyro = self.gyro
        if gyro is None:
            self.counters['imu_ignored'] += 1
            return []
        if t_ns <= 0:
            self._reject('imu_bad_stamp', f'Imu stamp is {"zero" if t_ns == 0 else "negative"}; '
                         'gyro sample ignored: check the IMU driver clock')
        elif t_ns - now_ns > self._future_ns:
            self._reject('imu_future_stamp',
                         f'Imu stamp is {(t_ns - now_ns) / NS_PER_S:.3f} s ahead of the node '
                         f'clock (future_tolerance {self.rules.future_tolerance_s:g} s); gyro '
                         'sample ignored')
        else:
            status = gyro.buffer.add(t_ns, yaw_rate)
            self.counters['imu_' + status.value] += 1
            if status is GyroStatus.CLOCK_RESET:
                self._warn('imu_clock_reset', f'the gyro clock stepped back by '
                           f'{gyro.buffer.stepped_back_s:.3f} s ({STEP_BACK_CONFIRM} samples in a '
                           'row; IMU driver restarted?): gyro history dropped, the gyro is used '
                           'again from its new clock')
            elif status is not GyroStatus.ACCEPTED:
                self._warn('imu_' + status.value,
                           f'gyro sample {status.value} (yaw rate {yaw_rate!r} rad/s, stamp '
                           f'{t_ns / NS_PER_S:.3f} s): not used')
        return self._drain(now_ns)

    def flush(self, now_ns: int) -> list[Estimate]:
        """Integrate the wheel samples that waited longer than imu.max_wait (node timer)."""
        return self._drain(now_ns)

    def _drain(self, now_ns: int) -> list[Estimate]:
        out = []
        pending = self._pending
        gyro = self.gyro
        wait_ns = (gyro.params.max_wait if gyro is not None else 0.0) * NS_PER_S
        while pending:
            t_ns, omega_l, omega_r, arrived_ns, check_jump = pending[0]
            if (gyro is not None and not gyro.buffer.ready(t_ns)
                    and now_ns - arrived_ns <= wait_ns):
                break
            pending.popleft()
            estimate = self._update_now(t_ns, omega_l, omega_r, check_jump)
            if estimate is not None:
                out.append(estimate)
        return out

    # ------------------------------------------------------------------ the pipeline
    def update(self, t_ns: int, omega_l: float, omega_r: float,
               now_ns: int | None = None, check_jump: bool = True) -> Estimate | None:
        """Integrate a stamped sample; return what to publish for it, if anything.

        With the gyro in use, a sample whose interval the gyro does not cover yet waits (at
        most imu.max_wait after ``now_ns``, its arrival; default: its stamp): it is then
        integrated by :meth:`imu_sample` or :meth:`flush`, which return its estimate.
        """
        if self.gyro is not None:
            arrived = t_ns if now_ns is None else now_ns
            if self._pending or not self.gyro.buffer.ready(t_ns):
                self._pending.append((t_ns, omega_l, omega_r, arrived, check_jump))
                if len(self._pending) > MAX_PENDING:  # never hold more than a few seconds
                    t, left, right, _, check = self._pending.popleft()
                    return self._update_now(t, left, right, check)
                return None
        return self._update_now(t_ns, omega_l, omega_r, check_jump)

    def _update_now(self, t_ns: int, omega_l: float, omega_r: float,
                    check_jump: bool = True) -> Estimate | None:
        last = self.last_input_t_ns
        if last is not None and last - t_ns > self._step_back_ns:
            if not self._clock_restarted(t_ns):
                return None
        elif self._step_back_run:
            self._step_back_run.clear()
        result = self.step(t_ns, omega_l, omega_r, check_jump)
        status = result.status
        if status is not SampleStatus.INTEGRATED:  # the usual case first: this runs per sample
            if not status.accepted:
                return None
            self.last_input_t_ns = t_ns
            if status is SampleStatus.DUPLICATE_STAMP:
                self._fresh()
                return None
        self.last_input_t_ns = t_ns
        self._fresh()
        return self._estimate(t_ns + self.integrator.output_offset_ns, result)

    def _clock_restarted(self, t_ns: int) -> bool:
        """Take a stamp far behind the last accepted one: True once a clock restart is confirmed.

        Until ``STEP_BACK_CONFIRM`` such samples in a row (increasing, each within max_dt of the
        previous) confirm it, the sample is rejected; then the odometry is reset to the origin
        and the sample is taken as the first of the new clock.
        """
        run = self._step_back_run
        if run and not 0 < t_ns - run[-1] <= self.integrator.limits.max_dt_s * NS_PER_S:
            run.clear()
        run.append(t_ns)
        behind_s = (self.last_input_t_ns - t_ns) / NS_PER_S
        if len(run) < STEP_BACK_CONFIRM:
            self._reject('stamp_step_back',
                         f'stamp {behind_s:.3f} s behind the last accepted one (more than '
                         f'max_stamp_step_back {self.rules.max_stamp_step_back_s:g} s): sample '
                         f'rejected; {STEP_BACK_CONFIRM} such samples in a row mean the driver '
                         'clock stepped back, and the odometry is reset')
            return False
        self.clock_changed()
        self.counters['stamp_reset'] += 1
        self._warn('stamp_reset', f'the input clock stepped back by {behind_s:.3f} s '
                   f'({STEP_BACK_CONFIRM} samples in a row; driver restarted?): odometry reset to '
                   'the origin')
        return True

    def step(self, t_ns: int, omega_l: float, omega_r: float,
             check_jump: bool = True) -> StepResult:
        """Integrate one sample and propagate the covariance; count and report the outcome.

        ``check_jump`` False: the speeds are a travel between encoder positions, not readings
        the wheel-jump rule applies to (or the reader applied it already).
        """
        result = self.integrator.step(t_ns, omega_l, omega_r, check_jump)
        status = result.status
        self.counters[status.value] += 1
        if status is SampleStatus.INTEGRATED:
            gyro = self.gyro
            if gyro is None:
                self.covariance.step(result.start_pose, result.step_twist, result.dt_s,
                                     wheels=result.step_wheels, jacobian=self._jacobian())
            else:
                result = self._aided(gyro, result)
            self.period_s = result.dt_s
            learner = self.learner
            if learner is not None and learner.wheel_step(t_ns, result.step_wheels,
                                                          result.step_twist):
                self.apply_learned()
            return result
        if self.learner is not None and status in (SampleStatus.FIRST, SampleStatus.GAP):
            self.learner.wheel_break(t_ns)
        if status is SampleStatus.GAP:
            self._warn('gap', result.detail)
        elif status is SampleStatus.NON_FINITE_STATE:
            self._warn('non_finite_state', f'{result.detail}; not published', error=True)
        elif not status.accepted:
            self._warn(status.value, f'wheel sample rejected: {result.detail}')
        return result

    def _jacobian(self) -> list[tuple[float, float, float]] | None:
        """Return d(twist)/dC of the step from its source state, else None.

        A residual model's coefficient uncertainty, or an online learner's whose twist reads
        the rate (``state_jacobian``): their twist depends on the state, not the speeds alone.
        """
        parameters = self.covariance.parameters
        if isinstance(parameters, ResidualUncertainty):
            return parameters.jacobian(self.integrator.step_state)
        state_jacobian = getattr(parameters, 'state_jacobian', None)
        return None if state_jacobian is None else state_jacobian(self.integrator.step_state)

    def _aided(self, gyro: GyroAid, result: StepResult) -> StepResult:
        """Count the gyro interval and propagate the covariance of the aided step.

        Published: the yaw rate integrated (fuse on the gyro) or the model's times the gain.
        """
        last = gyro.last
        self.counters['imu_interval_' + last.status.value] += 1
        if gyro.news:
            cause = ('imu_clock_ahead' if last.status is GyroStatus.CLOCK_AHEAD
                     else 'imu_contradicts')
            self._warn(cause, gyro.news, error=gyro.check.contradicts)
            gyro.news = ''
        vx, vy, w = result.step_twist
        dt_s = result.dt_s
        noise = self.covariance.noise
        extra = None
        if noise is not None:
            x, y, yaw = result.start_pose
            dx, dy = step_scalar(x, y, yaw, vx, vy, w, dt_s)[3:]
            ds = math.hypot(dx, dy)
            used = noise.step_variances(ds, w * dt_s, moving_time(vx, vy, w, dt_s))[2]
            model = noise.step_variances(ds, last.model_yaw_rate * dt_s, moving_time(
                vx, vy, last.model_yaw_rate, dt_s))[2]
            extra = (0.0, 0.0, 0.0, 0.0, 0.0, gyro.yaw_step_variance(model) - used)
        self.covariance.step(result.start_pose, result.step_twist, dt_s, extra,
                             result.step_wheels, self._jacobian())
        hx, hy, hw = result.twist
        published = w if last.yaw_from_gyro else gyro.filter.gain * hw
        return replace(result, twist=(hx, hy, published))

    def _estimate(self, t_ns: int, result: StepResult) -> Estimate | None:
        last = self.last_published_t_ns
        if self._min_period_ns and last is not None and t_ns - last < self._min_period_ns:
            self.counters['rate_limited'] += 1
            return None
        covariance = self.covariance
        pose_cov = covariance.pose_covariance_flat()
        twist_cov = covariance.twist_covariance_flat(result.twist, self.period_s)
        gyro = self.gyro
        if gyro is not None and covariance.calibrated and self.period_s > 0.0:
            twist_cov[35] = max(gyro.yaw_rate_variance(twist_cov[35], self.period_s,
                                                       gyro.last.model_yaw_rate),
                                TWIST_VARIANCE_FLOOR[2])
        x, y, yaw = result.pose
        vx, vy, w = result.twist
        # A sum of finite terms may overflow to inf only far beyond any plausible value.
        if not math.isfinite(x + y + yaw + vx + vy + w + sum(pose_cov) + sum(twist_cov)):
            self.counters['non_finite_output'] += 1
            self._warn('non_finite_output', 'odometry has a non-finite pose, twist or '
                       f'covariance (pose {result.pose}, twist {result.twist}); not published',
                       error=True)
            return None
        self.counters['published'] += 1
        self.last_published_t_ns = t_ns
        # tuple.__new__ skips the named tuple's Python-level __new__ (once per sample).
        return _new_estimate(Estimate, (t_ns, result.pose, result.twist, pose_cov, twist_cov))

    def _reject(self, cause: str, message: str) -> None:
        self.counters[cause] += 1
        self._warn(cause, message)

    # ------------------------------------------------------------------ offline
    def predict(self, wheels: WheelSamples, start: Sequence[float] = (0.0, 0.0, 0.0),
                imu: ImuSamples | None = None,
                restarts: Mapping[int, Sequence[float]] | None = None,
                reference: PoseTrack | None = None,
                jumps_dropped: bool = False,
                covariance_at: Container[int] | None = None) -> 'Prediction':
        """Restart at ``start`` and run every sample through :meth:`step`, as the node does.

        With the gyro in use, ``imu`` samples arrive in stamp order, as the node receives them:
        those stamped up to a wheel sample's stamp before it, then more while the wheel sample
        waits for its interval to be covered (at most imu.max_wait past its stamp). The gyro
        history and the learned gain and bias carry over from an earlier call (a drive cut in
        windows). ``restarts`` ({sample index: pose}): after that sample, the pose is set and its
        covariance zeroed, everything else kept (the windows of a NEES study); the prediction
        then holds the pose covariance and the gain after every sample. ``reference`` (online
        calibration, a learner attached): reference poses handed over in stamp order, those
        stamped up to a wheel sample's stamp before it, as the node receives them.
        ``jumps_dropped``: the
        reader applied the wheel-jump rule already, exempting speeds measured by encoder
        positions as the node does (a bag read with wheel_signal position or auto); the
        integrator then does not apply it again. ``covariance_at`` (sample indices): the
        covariances (and the gain) are read out after these samples only, NaN elsewhere; the
        propagation itself is unchanged, so the values read are the same (a calibration that
        needs them at window ends only skips the per-sample read-out).
        """
        self._restart(start)
        poses = np.empty((len(wheels), 3))
        twists = np.empty((len(wheels), 3))
        pose_covs = np.empty((len(wheels), 36))
        if covariance_at is not None:
            pose_covs.fill(np.nan)
        covariances = gains = None
        if restarts is not None:
            covariances = np.full((len(wheels), 3, 3), np.nan)
            gains = np.ones(len(wheels)) if covariance_at is None else np.full(len(wheels), np.nan)
        status = []
        gyro = self.gyro
        feed = _GyroFeed(gyro, imu, self.counters)
        references = _ReferenceFeed(self, reference)
        for i, (t_ns, omega_l, omega_r) in enumerate(zip(wheels.t_ns.tolist(), wheels.omega_l,
                                                         wheels.omega_r)):
            feed.until(t_ns)
            references.until(t_ns)
            result = self.step(int(t_ns), omega_l, omega_r, not jumps_dropped)
            poses[i] = result.pose
            twists[i] = result.twist
            status.append(result.status)
            read = covariance_at is None or i in covariance_at
            if read:
                pose_covs[i] = self.covariance.pose_covariance_flat()
            if restarts is not None:
                if read:
                    covariances[i] = self.covariance.total_cov()
                    gains[i] = gyro.filter.gain if gyro is not None else 1.0
                if i in restarts:
                    self.integrator.restart_pose(check_pose(restarts[i]))
                    self._reset_covariance(float(restarts[i][2]))
        offset_ns = self.output_offset_ns
        return Prediction(wheels.t_ns + offset_ns, poses, twists, tuple(status), offset_ns,
                          pose_covs.reshape(-1, 6, 6), covariances, gains)


def _controller(config: OdometryConfig) -> ControllerGeometry | None:
    """Return the drive controller's geometry for input odometry, else None."""
    if config['input'] != 'odometry':
        return None
    return ControllerGeometry.from_values(config.values)


def _propagator(config: OdometryConfig) -> PoseCovariancePropagator:
    return PoseCovariancePropagator(config.active_noise, config['pose_covariance_diagonal'],
                                    config['twist_covariance_diagonal'],
                                    config.active_parameter_uncertainty)


def predict_wheels(wheels: WheelSamples, source: TwistSource,
                   limits: IntegratorLimits | None = None,
                   start: Sequence[float] = (0.0, 0.0, 0.0), imu: ImuSamples | None = None,
                   imu_params: GyroParams | None = None,
                   wheel_radius_m: float = DEFAULT_GEOMETRY.wheel_radius,
                   interval: str = DEFAULT_INTERVAL) -> Prediction:
    """Run ``source`` over every wheel sample from ``start``, through the node's odometer."""
    return Odometer(source, limits, imu=imu_params, wheel_radius_m=wheel_radius_m,
                    interval=interval).predict(wheels, start, imu)
