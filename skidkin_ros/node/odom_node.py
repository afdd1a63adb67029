"""The live odometry node: wheel speeds in, calibrated nav_msgs/Odometry out.

The node is the ROS wiring around :class:`~skidkin_ros.core.odometry.odometer.Odometer`, which
holds every rule applied to a sample (stamping, wheel pairing, integration, covariance, what is
published) and which ``skidkin predict`` runs offline. Here: subscriptions, publishers, services,
timers, the clock and logging; parameters are declared in :mod:`skidkin_ros.node.parameters`,
the /diagnostics status is built in :mod:`skidkin_ros.node.diagnostics`.

Inputs (parameter ``input``, read-only after start-up):

* ``joint_state`` (default): sensor_msgs/JointState on ``joint_states``, integrated on
  ``header.stamp``; a side's speed is the mean of the velocities of its joints. Messages are
  read from their serialized form by :mod:`skidkin_ros.node.wire`; what it does not read goes
  to rclpy's deserializer, and what that refuses too is dropped and counted
  (``malformed_message``). A wheel joint listed twice makes the sample refused.
* ``wheel_topics``: std_msgs/Float64 on ``wheel/left/velocity`` and ``wheel/right/velocity``
  (rad/s), stamped with the node clock on receipt (honours use_sim_time) and paired within
  ``pair_tolerance``.
* ``odometry``: a drive controller's nav_msgs/Odometry on ``wheel_odom`` (remap it to e.g.
  ``/diff_drive_controller/odom``), on ``header.stamp``; the wheel speeds are recovered from its
  twist with the controller's own geometry (``controller.*``,
  :mod:`skidkin_ros.core.odometry.controller`). A NaN/inf twist is refused
  (``non_finite_twist``). No driver change: the calibrated odometry is published on ``odom``.

Optional gyro (``imu.mode`` adapt or fuse; off by default): sensor_msgs/Imu on ``imu/data``
(remappable), its ``angular_velocity.z`` taken as the base frame's yaw rate (the IMU mounted
z-up; ``imu.scale``, ``imu.bias``, ``imu.time_offset`` from ``skidkin calibrate``). The
subscription exists only while the mode is not off. A message whose
``angular_velocity_covariance[0]`` is -1 (the ROS convention for "no data") or with a zero,
negative or future stamp is refused; NaN/inf, saturated, older and duplicate rates are counted
and never used (the odometer's :class:`~skidkin_ros.core.odometry.gyro.GyroBuffer`). A wheel
sample whose interval the gyro does not cover yet waits at most ``imu.max_wait`` (checked on
every gyro message and on the 0.1 s watchdog tick); a stale gyro never stops the odometry (the
learned gain carries on). The gain and bias are on /diagnostics.

Optional reference (``online.enabled``; off by default): nav_msgs/Odometry on ``reference/odom``
(remappable; lidar odometry, a SLAM, GNSS), the pose of ``online.mount_*`` on the robot stamped
``online.time_offset`` late. The active model's parameters are learned from it online
(:mod:`skidkin_ros.core.online`); refused reference poses are counted by cause and never stop
the odometry. /diagnostics reports the state (learning, holding, adapting), the parameters and
their sigmas; ``~/save_calibration`` (std_srvs/Trigger) writes them as a parameters file
(``online.save_path``; never over an existing file).

Inputs use the sensor-data QoS (best-effort and reliable publishers both connect); QoS can be
overridden with the standard ``qos_overrides.<topic>.subscription.*`` parameters.

Outputs: nav_msgs/Odometry on ``odom`` (reliable), one per accepted sample with a new stamp
(capped by ``max_rate``), stamped with the sample stamp, twist in the child frame; covariance from
:class:`~skidkin_ros.core.odometry.propagation.PoseCovariancePropagator` (never all zeros);
optional TF (needs tf2_ros); /diagnostics at 1 Hz on a steady clock.

Services and topics: ``~/reset`` (std_srvs/Trigger) zeroes the pose and covariance and always
succeeds; it and ``~/set_pose`` change the pose and its covariance only: the last stamp and the
held speeds stay, so the next sample integrates the interval since the previous one (as
diff_drive_controller keeps its wheel baseline); only a new clock restarts. ``~/set_pose``
(geometry_msgs/PoseWithCovarianceStamped, like robot_localization's set_pose; there is no
standard service carrying a pose) sets the pose; a request with a NaN or
infinite field, x or y beyond 1e9 m, or a covariance that is not finite, bounded (1e12) and
positive semi-definite is rejected with a warning and counted in diagnostics.

While the input is stale (no accepted sample for ``input_timeout``), the pose is kept, nothing new
is published and /diagnostics reports STALE. When samples return, integration resumes from the
kept pose; a stamp gap longer than ``max_dt`` is not integrated across.
"""

from __future__ import annotations

import collections
import sys
import threading
import time
from typing import Any, Sequence

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
import numpy as np
from rcl_interfaces.msg import SetParametersResult
import rclpy
from rclpy.clock import Clock, ClockType, JumpThreshold, TimeJump
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
import rclpy.logging
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import Imu, JointState
from skidkin_ros.core.odometry.config import (check_model_given, default_parameters_warning,
                                              missing_parameters, models_held, OdometryConfig,
                                              switches_model)
from skidkin_ros.core.odometry.odometer import Estimate
from skidkin_ros.core.odometry.saved_grounds import GROUND_NAMES
from skidkin_ros.core.online import attach_online, online_odometer
from skidkin_ros.core.online.retune import retune
from skidkin_ros.core.timeunits import NS_PER_S, s_to_ns
from skidkin_ros.errors import ConfigError
from skidkin_ros.node.callbacks import guarded as _guarded, sensor_qos
from skidkin_ros.node.conversions import ns_to_stamp
from skidkin_ros.node.diagnostics import StatusReport
from skidkin_ros.node.inputs import InputCallbacks
from skidkin_ros.node.output import OdometryOutput
from skidkin_ros.node.parameters import (check_params_files, current_flat, declare_schema,
                                         parameter_descriptor, plain_value)
from skidkin_ros.node.requests import PoseRequests
from skidkin_ros.node.wire import JointStateReader
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

__all__ = ['OdomNode', 'main', 'check_params_files', 'parameter_descriptor', 'NODE_NAME']

NODE_NAME = 'odom_node'
DIAGNOSTICS_PERIOD_S = 1.0
WATCHDOG_PERIOD_S = 0.1
WARN_PERIOD_NS = NS_PER_S
OUTPUT_DEPTH = 10
EXIT_CONFIG = 2


class OdomNode(InputCallbacks, PoseRequests, Node):
    """Skid-steer wheel odometry with a calibrated kinematic model (see module docstring)."""

    def __init__(self, node_name: str = NODE_NAME, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._lock = threading.RLock()
        self.counters: collections.Counter[str] = collections.Counter()
        self.last_warnings: dict[str, str] = {}  # cause -> last message, for diagnostics
        self._warned_at: dict[str, int] = {}
        self._suppressed: collections.Counter[str] = collections.Counter()
        self._clock_waiting_logged = False
        try:
            self._schema = declare_schema(self)
            self._config = OdometryConfig.from_flat(current_flat(self, self._schema))
        except ConfigError:
            self.destroy_node()
            raise
        config = self._config
        # Models whose parameters were given (file, command line, later at runtime): the only
        # ones `model` may switch to (the others would run their defaults, an ideal drive).
        self._models_given = set(models_held(self._parameter_overrides))
        warning = default_parameters_warning(config.model, self._models_given,
                                             config.augmented_base)
        if warning is not None:
            self.get_logger().warning(warning)
        self._odometer = online_odometer(config, counters=self.counters, warn=self._warn,
                                         fresh=self._mark_fresh, note=self._note_signal)
        self._last_accepted_mono_ns: int | None = None
        self._stale = True
        self._stale_reported = False
        # The wheel joints' places in the last JointState name list (drivers repeat the list),
        # keyed by that list (a tuple of names; the reader returns the same tuple while the
        # serialized list is unchanged, so the comparison is cheap).
        self._joint_names: tuple[str, ...] | None = None
        self._joint_reader = JointStateReader()
        self._rclpy_read_logged = False
        self._joint_index: tuple[tuple[int, ...], tuple[int, ...]] = ((), ())
        self._side_seen_mono_ns: dict[str, int | None] = {'left': None, 'right': None}
        self._status_report = StatusReport()

        output_qos = QoSProfile(depth=OUTPUT_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
        overridable = QoSOverridingOptions.with_default_policies()
        self._output = OdometryOutput(self, output_qos, config['publish_tf'])
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', output_qos)
        self._input = config['input']
        if self._input == 'joint_state':
            # Serialized (raw): the node reads the few fields it needs itself (see node.wire).
            self.create_subscription(JointState, 'joint_states', self._on_joint_state,
                                     sensor_qos(), qos_overriding_options=overridable,
                                     raw=True)
        elif self._input == 'odometry':
            # A drive controller's odometry (remap wheel_odom to e.g.
            # /diff_drive_controller/odom); its twist gives back the wheel speeds.
            self.create_subscription(Odometry, 'wheel_odom', self._on_wheel_odometry,
                                     sensor_qos(), qos_overriding_options=overridable)
        else:
            self.create_subscription(Float64, 'wheel/left/velocity', self._on_left_wheel,
                                     sensor_qos(), qos_overriding_options=overridable)
            self.create_subscription(Float64, 'wheel/right/velocity', self._on_right_wheel,
                                     sensor_qos(), qos_overriding_options=overridable)
        self._imu_sub: Any = None
        self._sync_imu_subscription(config)
        self._reference_sub: Any = None
        self._sync_reference_subscription(config)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/save_calibration', self._on_save_calibration)
        self.create_subscription(PoseWithCovarianceStamped, '~/set_pose', self._on_set_pose,
                                 QoSProfile(depth=OUTPUT_DEPTH,
                                            reliability=ReliabilityPolicy.RELIABLE))
        # Watchdogs on a steady clock: a paused /clock or a stepped wall clock cannot stall them.
        self.steady_clock = Clock(clock_type=ClockType.STEADY_TIME)
        # One timer for both (each entity in the wait set costs the executor on every message).
        self.timer = self.create_timer(WATCHDOG_PERIOD_S, self._on_timer,
                                       clock=self.steady_clock)
        self._next_diagnostics_ns = time.monotonic_ns() + s_to_ns(DIAGNOSTICS_PERIOD_S)
        self._jump_handle = self.get_clock().create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1),
                          on_clock_change=True),
            post_callback=self._on_clock_jump)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.get_logger().info(
            f'odometry with model {config.model!r} (r {config.geometry.wheel_radius:g} m, '
            f'b {config.geometry.track_width:g} m), input {self._input}, '
            f'interval {config["interval"]}, '
            f'covariance {"calibrated" if config.active_noise else "fallback diagonals"}')

    # ------------------------------------------------------------------ parameters
    def _on_set_parameters(self, parameters: Sequence[rclpy.parameter.Parameter]
                           ) -> SetParametersResult:
        changes = {p.name: plain_value(p.value) for p in parameters if p.name in self._schema}
        if not changes:
            return SetParametersResult(successful=True)
        flat = current_flat(self, self._schema)
        flat.update(changes)
        given = self._models_given | set(models_held(changes))
        try:
            config = OdometryConfig.from_flat(flat)
            if switches_model(self._config, config):
                missing = missing_parameters(config.model, given, config.augmented_base)
                check_model_given(config.model, given, 'the parameters the node was given '
                                  f'(set its {missing} parameters first)', config.augmented_base)
        except ConfigError as err:
            self.get_logger().warning(f'parameter change rejected: {err}')
            return SetParametersResult(successful=False, reason=str(err))
        with self._lock:
            self._apply_config(config)
            self._models_given = given
        self.get_logger().info(f'parameters changed: {sorted(changes)}; model {config.model}')
        return SetParametersResult(successful=True)

    def _apply_config(self, config: OdometryConfig) -> None:
        """Switch to a validated configuration; the pose and its covariance are kept.

        Online calibration goes on with what it learned when neither the model, its parameters
        nor online.* (the remembered grounds included) changed, or only online.* gates did
        (``retune.KEEP``); otherwise it restarts from the parameters given.
        """
        old = self._config
        learner = self._odometer.learner
        self._odometer.configure(config)
        if (learner is not None and config.model == old.model
                and config.model_values == old.model_values
                and all(config[name] == old[name] for name in GROUND_NAMES)
                and (config.online == old.online  # a gate changed: kept (core/online/retune.py)
                     or retune(learner, old.online, config.online))):
            self._odometer.attach_learner(learner)
        else:
            attach_online(self._odometer, config, self._warn)
        if any(config[name] != old[name] for name in ('left_wheel_joints', 'right_wheel_joints')):
            # other joints: their positions are not differenced against the old joints' ones
            self._odometer.signal.clear()
        self._sync_imu_subscription(config)
        self._sync_reference_subscription(config)
        self._joint_names = None  # the wheel joints may have changed
        self._output.configure(config)
        self._config = config

    def _sync_imu_subscription(self, config: OdometryConfig) -> None:
        """Subscribe to the gyro while imu.mode is not off (no cost for a gyro not used)."""
        wanted = config['imu.mode'] != 'off'
        if wanted and self._imu_sub is None:
            self._imu_sub = self.create_subscription(
                Imu, 'imu/data', self._on_imu, sensor_qos(),
                qos_overriding_options=QoSOverridingOptions.with_default_policies())
            self.get_logger().info(f'imu.mode {config["imu.mode"]}: the gyro is read from '
                                   f'sensor_msgs/Imu on {self._imu_sub.topic_name}')
        elif not wanted and self._imu_sub is not None:
            self.destroy_subscription(self._imu_sub)
            self._imu_sub = None
            self.get_logger().info('imu.mode off: the gyro is no longer read')

    def _sync_reference_subscription(self, config: OdometryConfig) -> None:
        """Subscribe to the reference while online.enabled (no cost when off)."""
        wanted = config.online.enabled
        if wanted and self._reference_sub is None:
            self._reference_sub = self.create_subscription(
                Odometry, 'reference/odom', self._on_reference, sensor_qos(),
                qos_overriding_options=QoSOverridingOptions.with_default_policies())
            self.get_logger().info('online calibration on: learning from nav_msgs/Odometry on '
                                   f'{self._reference_sub.topic_name}')
        elif not wanted and self._reference_sub is not None:
            self.destroy_subscription(self._reference_sub)
            self._reference_sub = None
            self.get_logger().info('online calibration off: the reference is no longer read')

    @property
    def config(self) -> OdometryConfig:
        """Return the configuration in force."""
        return self._config

    @property
    def pose(self) -> np.ndarray:
        """Return the current (x, y, yaw) estimate."""
        with self._lock:
            return self._odometer.pose

    def _clock_now_ns(self) -> int | None:
        """Return the node clock in ns, or None while use_sim_time waits for /clock (N13)."""
        clock = self.get_clock()
        if not clock.ros_time_is_active:
            # ROS time without /clock is the system clock (CLOCK_REALTIME, as time.time_ns);
            # reading it directly skips rclpy's Time object: this runs once per wheel sample.
            return time.time_ns()
        now_ns = clock.now().nanoseconds
        if now_ns == 0:
            self.counters['waiting_for_clock'] += 1
            if not self._clock_waiting_logged:
                self._clock_waiting_logged = True
                self.get_logger().warning(
                    'use_sim_time is true but no /clock received yet: waiting for /clock; '
                    'wheel samples are not integrated until it arrives')
            return None
        return now_ns

    # ------------------------------------------------------------------ output
    def _mark_fresh(self) -> None:
        self._last_accepted_mono_ns = time.monotonic_ns()
        if self._stale and self._stale_reported:
            self.get_logger().info('wheel input resumed')
        self._stale = False
        self._stale_reported = False

    def _publish(self, estimate: Estimate) -> None:
        self._output.publish(estimate, self._config)

    @_guarded
    def _on_clock_jump(self, jump: TimeJump) -> None:
        """Reset on a backward jump or a clock change (e.g. a bag replayed in a loop, N12)."""
        clock_change, delta_ns = jump.clock_change, int(jump.delta.nanoseconds)
        with self._lock:
            self._odometer.clock_changed()  # the stamps of the old clock mean nothing now
            self.counters['clock_jump'] += 1
        if delta_ns < 0:
            self.get_logger().warning(
                f'clock jumped back by {-delta_ns / NS_PER_S:.3f} s (bag replayed in a loop?): '
                'odometry reset to the origin')
        else:
            self.get_logger().warning(f'clock source changed ({clock_change}): odometry reset '
                                      'to the origin')

    # ------------------------------------------------------------------ faults and reporting
    def _reject(self, cause: str, message: str) -> None:
        self.counters[cause] += 1
        self._warn(cause, message)

    def _note_signal(self, message: str) -> None:
        """Say which wheel signal is integrated, when that changes (wheel_signal auto)."""
        self.get_logger().info(message)

    def _warn(self, cause: str, message: str, error: bool = False) -> None:
        """Log at most once a second per cause, saying how many were suppressed."""
        self.last_warnings[cause] = message
        now = time.monotonic_ns()
        last = self._warned_at.get(cause)
        if last is not None and now - last < WARN_PERIOD_NS:
            self._suppressed[cause] += 1
            return
        suppressed = self._suppressed.pop(cause, 0)
        if suppressed:
            message += f' ({suppressed} more like this since the last message)'
        self._warned_at[cause] = now
        if error:
            self.get_logger().error(message)
        else:
            self.get_logger().warning(message)

    def _callback_failed(self, where: str, err: Exception) -> None:
        with self._lock:
            self.counters['callback_error'] += 1
            count = self.counters['callback_error']
        first = count == 1
        text = (f'{where} failed on a message and dropped it: {type(err).__name__}: {err} '
                f'({count} callback error(s) so far); the node keeps running')
        if first:
            self.get_logger().error(text)
        else:
            self._warn('callback_error', text, error=True)

    def _on_timer(self) -> None:
        """Run the input watchdog every tick and publish /diagnostics every second."""
        self._on_watchdog()
        self._flush_waiting()
        now_ns = time.monotonic_ns()
        if now_ns >= self._next_diagnostics_ns:
            period_ns = s_to_ns(DIAGNOSTICS_PERIOD_S)
            # Keep the cadence; after a long stall, restart it instead of catching up.
            self._next_diagnostics_ns = max(self._next_diagnostics_ns + period_ns,
                                            now_ns + period_ns // 2)
            self._on_diagnostics()

    @_guarded
    def _flush_waiting(self) -> None:
        """Integrate wheel samples that waited imu.max_wait for the gyro in vain."""
        with self._lock:
            if self._odometer.gyro is None:
                return
            now_ns = self._clock_now_ns()
            if now_ns is None:
                return
            for estimate in self._odometer.flush(now_ns):
                self._publish(estimate)

    @_guarded
    def _on_watchdog(self) -> None:
        with self._lock:
            age_s = self.last_sample_age_s()
            if age_s is None or age_s <= self._config['input_timeout']:
                return
            self._stale = True
            if not self._stale_reported:
                self._stale_reported = True
                self.get_logger().warning(
                    f'no accepted wheel sample for {age_s:.2f} s (input_timeout '
                    f'{self._config["input_timeout"]:g} s): input stale; keeping the pose, '
                    'publishing nothing new until samples return')

    def last_sample_age_s(self) -> float | None:
        """Return the steady-clock age (s) of the last accepted sample, None if none yet."""
        if self._last_accepted_mono_ns is None:
            return None
        return (time.monotonic_ns() - self._last_accepted_mono_ns) / NS_PER_S

    def diagnostic_status(self) -> DiagnosticStatus:
        """Return the current status (also published on /diagnostics) and start a new period."""
        with self._lock:
            age_s = self.last_sample_age_s()
            stale = self._stale or age_s is None or age_s > self._config['input_timeout']
            side_ages = None
            if self._input == 'wheel_topics':
                now = time.monotonic_ns()
                side_ages = {side: None if seen is None else (now - seen) / NS_PER_S
                             for side, seen in self._side_seen_mono_ns.items()}
            gyro = self._odometer.gyro
            imu = None
            if gyro is not None:
                imu = gyro.state()
                newest = gyro.buffer.newest_ns
                now_ns = self._clock_now_ns()
                imu['newest_age_s'] = (float('nan') if newest is None or now_ns is None
                                       else (now_ns - newest) / NS_PER_S)
                imu['at_bound'] = float(gyro.filter.at_bound)
            learner = self._odometer.learner
            online = None if learner is None else learner.summary()
            return self._status_report.status(
                f'{self.get_fully_qualified_name()}: wheel odometry', self._config,
                self.counters, stale, age_s, side_ages, self._odometer.signal.in_use, imu,
                online)

    @_guarded
    def _on_diagnostics(self) -> None:
        array = DiagnosticArray()
        now_ns = self.get_clock().now().nanoseconds
        array.header.stamp = ns_to_stamp(max(now_ns, 0))
        array.status = [self.diagnostic_status()]
        self._diag_pub.publish(array)

    def destroy_node(self) -> None:
        """Unregister the clock jump handle, then destroy the node."""
        handle = getattr(self, '_jump_handle', None)
        if handle is not None:
            handle.unregister()
            self._jump_handle = None
        super().destroy_node()


def main(args: Sequence[str] | None = None) -> int:
    """Run the node; return 0, or 2 on a configuration error (one log line, no traceback)."""
    logger = rclpy.logging.get_logger(NODE_NAME)
    warnings: list[str] = []
    problems = check_params_files(sys.argv if args is None else args, warnings)
    for warning in warnings:
        logger.warning(warning)
    if problems:
        for problem in problems:
            logger.fatal(f'{problem}; the node did not start')
        return EXIT_CONFIG
    try:
        rclpy.init(args=args)
    except RuntimeError as err:  # rclpy's RCLError: malformed --ros-args
        logger.fatal(f'cannot parse the command line: {" ".join(str(err).split())}')
        return EXIT_CONFIG
    node = None
    code = 0
    try:
        node = OdomNode()
        rclpy.spin(node)
    except ConfigError as err:
        logger.fatal(f'invalid configuration: {err}; the node did not start')
        code = EXIT_CONFIG
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main())
