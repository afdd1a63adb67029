"""The live odometry node: wheel speeds in, calibrated nav_msgs/Odometry out.

Inputs (parameter ``input``, read-only after start-up):

* ``joint_state`` (default): sensor_msgs/JointState on ``joint_states``, integrated on
  ``header.stamp``; a side's speed is the mean of the velocities of its joints.
* ``wheel_topics``: std_msgs/Float64 on ``wheel/left/velocity`` and ``wheel/right/velocity``
  (rad/s), stamped with the node clock on receipt (honours use_sim_time) and paired within
  ``pair_tolerance``.

Inputs use the sensor-data QoS (best-effort and reliable publishers both connect); QoS can be
overridden with the standard ``qos_overrides.<topic>.subscription.*`` parameters.

Outputs: nav_msgs/Odometry on ``odom`` (reliable), one per accepted sample with a new stamp
(capped by ``max_rate``), stamped with the sample stamp, twist in the child frame; covariance from
:class:`~skidkin_ros.core.odometry.propagation.PoseCovariancePropagator` (never all zeros);
optional TF (needs tf2_ros); /diagnostics at 1 Hz on a steady clock.

Services and topics: ``~/reset`` (std_srvs/Trigger) zeroes the pose and covariance and always
succeeds. ``~/set_pose`` (geometry_msgs/PoseWithCovarianceStamped, like robot_localization's
set_pose; there is no standard service carrying a pose) sets the pose; a request with a NaN or
infinite field is rejected with a warning and counted in diagnostics.

While the input is stale (no accepted sample for ``input_timeout``), the pose is kept, nothing new
is published and /diagnostics reports STALE. When samples return, integration resumes from the
kept pose; a stamp gap longer than ``max_dt`` is not integrated across.
"""

from __future__ import annotations

import collections
import functools
import math
import sys
import threading
import time
from typing import Any, Callable, Sequence

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped
from nav_msgs.msg import Odometry
import numpy as np
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, SetParametersResult
import rclpy
from rclpy.clock import Clock, ClockType, JumpThreshold, TimeJump
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
import rclpy.logging
from rclpy.node import Node
from rclpy.qos import (qos_profile_sensor_data, QoSProfile, ReliabilityPolicy)
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState
from skidkin_ros.core.kinematics.specs import Geometry, GEOMETRY_SPECS
from skidkin_ros.core.odometry.config import OdometryConfig, parameter_schema, SchemaEntry
from skidkin_ros.core.odometry.integrator import (IntegratorLimits, SampleStatus, StepResult,
                                                  StreamingIntegrator)
from skidkin_ros.core.odometry.propagation import PoseCovariancePropagator
from skidkin_ros.core.rotation import yaw_to_quaternion
from skidkin_ros.errors import ConfigError
from skidkin_ros.node.conversions import (check_velocity_count, joint_indices, MissingJointError,
                                          ns_to_stamp, plain_value, planar_covariance_from_msg,
                                          planar_pose_from_msg, speeds_at, stamp_to_ns)
from skidkin_ros.node.wire import JointStateReader, OdometryWriter, WireFormatError
from std_msgs.msg import Float64
from std_srvs.srv import Trigger
import yaml

__all__ = ['OdomNode', 'main', 'check_params_files', 'parameter_descriptor', 'NODE_NAME']

NODE_NAME = 'odom_node'
NS_PER_S = 1_000_000_000
DIAGNOSTICS_PERIOD_S = 1.0
WATCHDOG_PERIOD_S = 0.1
WARN_PERIOD_NS = NS_PER_S
OUTPUT_DEPTH = 10
EXIT_CONFIG = 2

# Counter names reported on /diagnostics; which of them make the status WARN or ERROR.
WARN_CAUSES = ('non_finite', 'implausible', 'older', 'gap', 'zero_stamp', 'future_stamp',
               'missing_joint', 'unpaired', 'waiting_for_clock', 'set_pose_rejected')
ERROR_CAUSES = ('non_finite_state', 'non_finite_output', 'callback_error')
# Parameters that cannot change while running (the subscriptions depend on them).
READ_ONLY = ('input',)


def parameter_descriptor(entry: SchemaEntry) -> ParameterDescriptor:
    """Return the ROS parameter descriptor of one schema entry.

    Floating-point parameters use dynamic typing so that ``1`` in a YAML file (an integer to
    rclpy) is accepted and converted; the node validates every value itself through
    :meth:`OdometryConfig.from_flat`. A FloatingPointRange is attached only when both bounds are
    finite (rclpy cannot express an open or infinite range).
    """
    descriptor = ParameterDescriptor(name=entry.name, description=entry.description,
                                     read_only=entry.name in READ_ONLY)
    if entry.kind in ('double', 'double_array'):
        descriptor.dynamic_typing = True
        descriptor.additional_constraints = 'integers are accepted and converted to floats'
    spec = entry.spec
    if (entry.kind == 'double' and spec is not None and math.isfinite(spec.lower)
            and math.isfinite(spec.upper)):
        descriptor.floating_point_range = [
            FloatingPointRange(from_value=float(spec.lower), to_value=float(spec.upper),
                               step=0.0)]
        if spec.lower_open or spec.upper_open:
            descriptor.additional_constraints += f'; allowed range {spec.range_text()}'
    if entry.choices:
        descriptor.additional_constraints = 'one of: ' + ', '.join(entry.choices)
    if entry.kind == 'double_array':
        descriptor.additional_constraints += f'; exactly {entry.length} values > 0'
    return descriptor


def _guarded(method: Callable) -> Callable:
    """Wrap a callback so an unexpected exception is counted and logged, never fatal (N15)."""
    @functools.wraps(method)
    def wrapper(self: 'OdomNode', *args: Any) -> Any:
        try:
            return method(self, *args)
        except Exception as err:  # noqa: B902 - a callback must never kill the node
            self._callback_failed(method.__name__, err)
            return None
    return wrapper


class OdomNode(Node):
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
            self._schema = self._declare_parameters()
            self._config = OdometryConfig.from_flat(self._current_flat())
        except ConfigError:
            self.destroy_node()
            raise
        config = self._config
        self._integrator = StreamingIntegrator(config.bound_model(), self._limits(config))
        self._covariance = self._new_propagator(config)
        self._period_s = 0.0
        self._last_published_t_ns: int | None = None
        self._last_accepted_mono_ns: int | None = None
        self._stale = True
        self._stale_reported = False
        self._pending: dict[str, tuple[int, float] | None] = {'left': None, 'right': None}
        # The wheel joints' places in the last JointState name list (drivers repeat the list),
        # keyed by that list (its serialized bytes when the message came serialized).
        self._joint_key: Any = None
        self._joint_reader = JointStateReader()
        self._joint_index: tuple[tuple[int, ...], tuple[int, ...]] = ((), ())
        self._side_seen_mono_ns: dict[str, int | None] = {'left': None, 'right': None}
        self._report_counters: collections.Counter[str] = collections.Counter()
        self._report_mono_ns = time.monotonic_ns()

        output_qos = QoSProfile(depth=OUTPUT_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
        overridable = QoSOverridingOptions.with_default_policies()
        self._odom_pub = self.create_publisher(Odometry, 'odom', output_qos,
                                               qos_overriding_options=overridable)
        self._odom_msg = Odometry()
        # Serializer of the output for the frames in force (None: publish message objects).
        self._odom_writer: OdometryWriter | None = None
        self._writer_frames: tuple[str, str] | None = None
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', output_qos)
        self._tf_broadcaster = self._make_tf_broadcaster(config['publish_tf'])
        self._input = config['input']
        if self._input == 'joint_state':
            # Serialized (raw): the node reads the few fields it needs itself (see node.wire).
            self.create_subscription(JointState, 'joint_states', self._on_joint_state,
                                     qos_profile_sensor_data, qos_overriding_options=overridable,
                                     raw=True)
        else:
            self.create_subscription(Float64, 'wheel/left/velocity', self._on_left_wheel,
                                     qos_profile_sensor_data, qos_overriding_options=overridable)
            self.create_subscription(Float64, 'wheel/right/velocity', self._on_right_wheel,
                                     qos_profile_sensor_data, qos_overriding_options=overridable)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_subscription(PoseWithCovarianceStamped, '~/set_pose', self._on_set_pose,
                                 QoSProfile(depth=OUTPUT_DEPTH,
                                            reliability=ReliabilityPolicy.RELIABLE))
        # Watchdogs on a steady clock: a paused /clock or a stepped wall clock cannot stall them.
        self.steady_clock = Clock(clock_type=ClockType.STEADY_TIME)
        # One timer for both (each entity in the wait set costs the executor on every message).
        self.timer = self.create_timer(WATCHDOG_PERIOD_S, self._on_timer,
                                       clock=self.steady_clock)
        self._next_diagnostics_ns = time.monotonic_ns() + int(DIAGNOSTICS_PERIOD_S * NS_PER_S)
        self._jump_handle = self.get_clock().create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1),
                          on_clock_change=True),
            post_callback=self._on_clock_jump)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.get_logger().info(
            f'odometry with model {config.model!r} (r {config.geometry.wheel_radius:g} m, '
            f'b {config.geometry.track_width:g} m), input {self._input}, '
            f'covariance {"calibrated" if config.active_noise else "fallback diagonals"}')

    # ------------------------------------------------------------------ parameters
    def _declare_parameters(self) -> dict[str, SchemaEntry]:
        """Declare the whole schema (geometry first: model defaults follow it)."""
        self._check_overrides()
        geometry_entries = {entry.name: entry for entry in parameter_schema()
                            if entry.name in {spec.name for spec in GEOMETRY_SPECS}}
        for entry in geometry_entries.values():
            self._declare(entry)
        geometry = Geometry(**{name: float(self.get_parameter(name).value)
                               for name in geometry_entries})
        schema = {entry.name: entry for entry in parameter_schema(geometry)}
        for name, entry in schema.items():
            if name not in geometry_entries:
                self._declare(entry)
        return schema

    def _declare(self, entry: SchemaEntry) -> None:
        try:
            self.declare_parameter(entry.name, entry.default, parameter_descriptor(entry))
        except ParameterException as err:
            raise ConfigError(f'parameter {entry.name!r} was refused by ROS: {err}; '
                              f'{entry.description}') from err

    def _check_overrides(self) -> None:
        """Validate the values given on the command line / in files before declaring them.

        This gives one clear message naming the parameter and its range (instead of rclpy's
        type or range exception) and refuses names the node does not know (typos).
        """
        builtin = set(self._parameters)  # declared by rclpy itself (use_sim_time, ...)
        overrides = {name: plain_value(param.value)
                     for name, param in self._parameter_overrides.items()
                     if name not in builtin}
        OdometryConfig.from_flat(overrides)

    def _current_flat(self) -> dict[str, Any]:
        return {name: plain_value(self.get_parameter(name).value) for name in self._schema}

    def _on_set_parameters(self, parameters: Sequence[rclpy.parameter.Parameter]
                           ) -> SetParametersResult:
        changes = {p.name: plain_value(p.value) for p in parameters if p.name in self._schema}
        if not changes:
            return SetParametersResult(successful=True)
        flat = self._current_flat()
        flat.update(changes)
        try:
            config = OdometryConfig.from_flat(flat)
        except ConfigError as err:
            self.get_logger().warning(f'parameter change rejected: {err}')
            return SetParametersResult(successful=False, reason=str(err))
        with self._lock:
            self._apply_config(config)
        self.get_logger().info(f'parameters changed: {sorted(changes)}; model {config.model}')
        return SetParametersResult(successful=True)

    @staticmethod
    def _limits(config: OdometryConfig) -> IntegratorLimits:
        return IntegratorLimits(max_dt_s=config['max_dt'],
                                max_wheel_speed_rad_s=config['max_wheel_speed'])

    @staticmethod
    def _new_propagator(config: OdometryConfig) -> PoseCovariancePropagator:
        return PoseCovariancePropagator(config.active_noise, config['pose_covariance_diagonal'],
                                        config['twist_covariance_diagonal'])

    def _apply_config(self, config: OdometryConfig) -> None:
        """Switch to a validated configuration; the pose and its covariance are kept."""
        self._integrator.set_source(config.bound_model())
        self._integrator.limits = self._limits(config)
        covariance = self._new_propagator(config)
        covariance.cov = self._covariance.cov.copy()
        self._covariance = covariance
        self._joint_key = None  # the wheel joints may have changed
        if config['publish_tf'] and self._tf_broadcaster is None:
            self._tf_broadcaster = self._make_tf_broadcaster(True)
        self._config = config

    @property
    def config(self) -> OdometryConfig:
        """Return the configuration in force."""
        return self._config

    @property
    def pose(self) -> np.ndarray:
        """Return the current (x, y, yaw) estimate."""
        with self._lock:
            return self._integrator.pose.copy()

    # ------------------------------------------------------------------ inputs
    @_guarded
    def _on_joint_state(self, msg: bytes | JointState) -> None:
        """Take a JointState, serialized (the subscription's form) or as a message."""
        t_ns, n_names, key, names, velocity = self._joint_state_fields(msg)
        with self._lock:
            self.counters['received'] += 1
            config = self._config
            check_velocity_count(n_names, len(velocity))  # raises: reported by _guarded
            if key != self._joint_key:
                if names is None:
                    names = self._joint_reader.names(key)
                try:
                    self._joint_index = joint_indices(names, config['left_wheel_joints'],
                                                      config['right_wheel_joints'])
                except MissingJointError as err:
                    self._reject('missing_joint', str(err))
                    return
                self._joint_key = key
            omega_l, omega_r = speeds_at(velocity, *self._joint_index)
            now_ns = self._clock_now_ns()
            if now_ns is None:
                return
            if t_ns == 0:
                if not config['zero_stamp_uses_receive_time']:
                    self._reject('zero_stamp', 'JointState header.stamp is zero; sample '
                                 'rejected (set zero_stamp_uses_receive_time to use the receive '
                                 'time instead)')
                    return
                t_ns = now_ns
            ahead_ns = t_ns - now_ns
            if ahead_ns > config['future_tolerance'] * NS_PER_S:
                self._reject('future_stamp',
                             f'JointState stamp is {ahead_ns / NS_PER_S:.3f} s ahead of the node '
                             f'clock (future_tolerance {config["future_tolerance"]:g} s); '
                             'sample rejected: check the clocks of the driver and this machine')
                return
            self._process(t_ns, omega_l, omega_r)

    def _joint_state_fields(self, msg: bytes | JointState
                            ) -> tuple[int, int, Any, list[str] | None, Sequence[float]]:
        """Return (stamp ns, name count, name-list key, names or None, velocities).

        Serialized input is read by node.wire (names decoded later, only when the key changes);
        what it cannot read is deserialized by rclpy, like a message object.
        """
        if isinstance(msg, bytes):
            try:
                t_ns, n_names, key, velocity = self._joint_reader.read(msg)
                return t_ns, n_names, key, None, velocity
            except WireFormatError:  # not plain CDR: rclpy's deserialization decides
                msg = deserialize_message(msg, JointState)
        names = list(msg.name)
        return stamp_to_ns(msg.header.stamp), len(names), tuple(names), names, msg.velocity

    @_guarded
    def _on_left_wheel(self, msg: Float64) -> None:
        self._on_wheel('left', msg.data)

    @_guarded
    def _on_right_wheel(self, msg: Float64) -> None:
        self._on_wheel('right', msg.data)

    def _on_wheel(self, side: str, omega_rad_s: float) -> None:
        """Pair the two Float64 streams within pair_tolerance (N9)."""
        with self._lock:
            self.counters['received'] += 1
            now_ns = self._clock_now_ns()
            if now_ns is None:
                return
            other = 'right' if side == 'left' else 'left'
            self._side_seen_mono_ns[side] = time.monotonic_ns()
            tolerance_ns = self._config['pair_tolerance'] * NS_PER_S
            partner = self._pending[other]
            if partner is not None and abs(now_ns - partner[0]) <= tolerance_ns:
                self._pending[other] = None
                omega = {side: float(omega_rad_s), other: partner[1]}
                self._process(max(now_ns, partner[0]), omega['left'], omega['right'])
                return
            if self._pending[side] is not None or partner is not None:
                seen = self._side_seen_mono_ns[other]
                age = ('never received' if seen is None
                       else f'last sample {(time.monotonic_ns() - seen) / NS_PER_S:.3f} s ago')
                self._reject('unpaired',
                             f'{other} wheel speed is stale ({age}); not integrating until both '
                             f'sides arrive within pair_tolerance '
                             f'{self._config["pair_tolerance"]:g} s')
            self._pending[side] = (now_ns, float(omega_rad_s))
            if partner is not None and now_ns - partner[0] > tolerance_ns:
                self._pending[other] = None

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

    # ------------------------------------------------------------------ integration
    def _process(self, t_ns: int, omega_l: float, omega_r: float) -> None:
        result = self._integrator.step(t_ns, omega_l, omega_r)
        status = result.status
        self.counters[status.value] += 1
        if status is SampleStatus.NON_FINITE_STATE:
            self._warn('non_finite_state', f'{result.detail}; not published', error=True)
            return
        if not status.accepted:
            self._warn(status.value, f'wheel sample rejected: {result.detail}')
            return
        if status is SampleStatus.INTEGRATED:
            self._covariance.step(result.start_pose, result.step_twist, result.dt_s)
            self._period_s = result.dt_s
        elif status is SampleStatus.GAP:
            self._warn('gap', result.detail)
        self._mark_fresh()
        if status is SampleStatus.DUPLICATE_STAMP:
            return  # held speeds updated; a second message with the same stamp would confuse EKFs
        # With a time offset (augmented model) the pose integrated to t is the pose at t + offset.
        self._publish(t_ns + self._integrator.output_offset_ns, result)

    def _mark_fresh(self) -> None:
        self._last_accepted_mono_ns = time.monotonic_ns()
        if self._stale and self._stale_reported:
            self.get_logger().info('wheel input resumed')
        self._stale = False
        self._stale_reported = False

    def _publish(self, t_ns: int, result: StepResult) -> None:
        config = self._config
        max_rate = config['max_rate']
        if (max_rate > 0.0 and self._last_published_t_ns is not None
                and t_ns - self._last_published_t_ns < NS_PER_S / max_rate):
            self.counters['rate_limited'] += 1
            return
        pose_cov = self._covariance.pose_covariance_flat()
        twist_cov = self._covariance.twist_covariance_flat(result.twist, self._period_s)
        x, y, yaw = result.pose
        vx, vy, w = result.twist
        # A sum of finite terms may overflow to inf only far beyond any plausible value.
        if not math.isfinite(x + y + yaw + vx + vy + w + sum(pose_cov) + sum(twist_cov)):
            self.counters['non_finite_output'] += 1
            self._warn('non_finite_output', 'odometry has a non-finite pose, twist or '
                       f'covariance (pose {result.pose}, twist {result.twist}); not published',
                       error=True)
            return
        qx, qy, qz, qw = yaw_to_quaternion(yaw)
        writer = self._writer(config)
        if writer is not None:
            self._odom_pub.publish(writer.pack(t_ns, x, y, qz, qw, pose_cov, vx, vy, w,
                                               twist_cov))
        else:
            self._odom_pub.publish(self._odometry_msg(t_ns, x, y, qz, qw, pose_cov, vx, vy, w,
                                                      twist_cov))
        self.counters['published'] += 1
        self._last_published_t_ns = t_ns
        if self._tf_broadcaster is not None and config['publish_tf']:
            transform = TransformStamped()
            transform.header.stamp = ns_to_stamp(t_ns)
            transform.header.frame_id = config['odom_frame_id']
            transform.child_frame_id = config['base_frame_id']
            transform.transform.translation.x = x
            transform.transform.translation.y = y
            transform.transform.rotation.z = qz
            transform.transform.rotation.w = qw
            self._tf_broadcaster.sendTransform(transform)

    def _writer(self, config: OdometryConfig) -> OdometryWriter | None:
        """Return the serializer for the configured frames (None: publish messages instead)."""
        frames = (config['odom_frame_id'], config['base_frame_id'])
        if frames != self._writer_frames:
            writer: OdometryWriter | None = OdometryWriter(*frames)
            if not writer.agrees_with(deserialize_message, Odometry):
                self.get_logger().warning(
                    'the Odometry serializer disagrees with rclpy on this middleware: '
                    'publishing message objects instead (slower)')
                writer = None
            self._odom_writer, self._writer_frames = writer, frames
        return self._odom_writer

    def _odometry_msg(self, t_ns: int, x: float, y: float, qz: float, qw: float,
                      pose_cov: Sequence[float], vx: float, vy: float, w: float,
                      twist_cov: Sequence[float]) -> Odometry:
        msg = self._odom_msg  # reused: publish() serializes it before returning
        config = self._config
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t_ns, NS_PER_S)
        msg.header.frame_id = config['odom_frame_id']
        msg.child_frame_id = config['base_frame_id']
        msg.pose.pose.position.x = x
        msg.pose.pose.position.y = y
        msg.pose.pose.orientation.z = qz
        msg.pose.pose.orientation.w = qw
        msg.pose.covariance = np.array(pose_cov)
        msg.twist.twist.linear.x = vx
        msg.twist.twist.linear.y = vy
        msg.twist.twist.angular.z = w
        msg.twist.covariance = np.array(twist_cov)
        return msg

    def _make_tf_broadcaster(self, wanted: bool) -> Any:
        if not wanted:
            return None
        try:
            from tf2_ros import TransformBroadcaster
        except ImportError:
            self.get_logger().warning(
                'publish_tf is true but tf2_ros is not installed: the odom -> base transform is '
                'not broadcast (install ros-jazzy-tf2-ros); odometry is published as usual')
            return None
        return TransformBroadcaster(self)

    # ------------------------------------------------------------------ pose requests
    @_guarded
    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        with self._lock:
            self._reset_state((0.0, 0.0, 0.0))
            self.counters['reset'] += 1
        self.get_logger().info('odometry reset to the origin')
        response.success = True
        response.message = 'pose and covariance reset to zero'
        return response

    @_guarded
    def _on_set_pose(self, msg: PoseWithCovarianceStamped) -> None:
        try:
            pose = planar_pose_from_msg(msg.pose.pose)
        except ValueError as err:
            with self._lock:
                self._reject('set_pose_rejected', f'set_pose rejected: {err}')
            return
        with self._lock:
            self._reset_state(pose)
            block = planar_covariance_from_msg(msg.pose.covariance)
            if block is not None:
                self._covariance.cov = self._covariance.cov + block
            self.counters['set_pose'] += 1
        self.get_logger().info(f'pose set to x {pose[0]:.3f} m, y {pose[1]:.3f} m, '
                               f'yaw {pose[2]:.3f} rad')

    def _reset_state(self, pose: Sequence[float]) -> None:
        self._integrator.reset(pose)
        self._covariance.reset()
        self._period_s = 0.0
        self._last_published_t_ns = None
        self._pending = {'left': None, 'right': None}

    @_guarded
    def _on_clock_jump(self, jump: TimeJump) -> None:
        """Reset on a backward jump or a clock change (e.g. a bag replayed in a loop, N12)."""
        clock_change, delta_ns = jump.clock_change, int(jump.delta.nanoseconds)
        with self._lock:
            self._reset_state((0.0, 0.0, 0.0))
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
        now_ns = time.monotonic_ns()
        if now_ns >= self._next_diagnostics_ns:
            period_ns = int(DIAGNOSTICS_PERIOD_S * NS_PER_S)
            # Keep the cadence; after a long stall, restart it instead of catching up.
            self._next_diagnostics_ns = max(self._next_diagnostics_ns + period_ns,
                                            now_ns + period_ns // 2)
            self._on_diagnostics()

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
            now = time.monotonic_ns()
            period_s = max((now - self._report_mono_ns) / NS_PER_S, 1e-9)
            recent = self.counters - self._report_counters
            self._report_counters = collections.Counter(self.counters)
            self._report_mono_ns = now
            age_s = self.last_sample_age_s()
            stale = self._stale or age_s is None or age_s > self._config['input_timeout']
            level, summary = self._level(recent, stale)
            status = DiagnosticStatus(level=level, name=f'{self.get_fully_qualified_name()}: '
                                      'wheel odometry', message=summary,
                                      hardware_id=self._config['robot'])
            values = {
                'model': self._config.model,
                'input': self._input,
                'covariance': 'calibrated' if self._config.active_noise else 'fallback',
                'rate_hz': f'{recent["published"] / period_s:.2f}',
                'accepted_rate_hz': f'{self._accepted(recent) / period_s:.2f}',
                'last_sample_age_s': 'none' if age_s is None else f'{age_s:.3f}',
            }
            for side in ('left', 'right'):
                seen = self._side_seen_mono_ns[side]
                if self._input == 'wheel_topics':
                    values[f'{side}_age_s'] = ('none' if seen is None
                                               else f'{(now - seen) / NS_PER_S:.3f}')
            for name in sorted(self.counters):
                values[f'count.{name}'] = str(self.counters[name])
            status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
            return status

    @staticmethod
    def _accepted(counts: collections.Counter[str]) -> int:
        return sum(counts[s.value] for s in SampleStatus if s.accepted)

    def _level(self, recent: collections.Counter[str], stale: bool) -> tuple[bytes, str]:
        errors = {c: recent[c] for c in ERROR_CAUSES if recent[c]}
        warnings = {c: recent[c] for c in WARN_CAUSES if recent[c]}
        if stale:
            return DiagnosticStatus.STALE, 'no wheel input within input_timeout: pose held'
        if errors:
            return DiagnosticStatus.ERROR, f'errors in the last period: {errors}'
        if warnings:
            return DiagnosticStatus.WARN, f'samples rejected in the last period: {warnings}'
        return DiagnosticStatus.OK, 'integrating'

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


def check_params_files(argv: Sequence[str]) -> list[str]:
    """Return one problem per ``--params-file`` path that is missing or unreadable (N16)."""
    problems = []
    args = list(argv)
    for i, arg in enumerate(args):
        if arg != '--params-file':
            continue
        if i + 1 >= len(args):
            problems.append('--params-file is given without a path')
            continue
        path = args[i + 1]
        try:
            with open(path, encoding='utf-8') as stream:
                yaml.safe_load(stream)
        except FileNotFoundError:
            problems.append(f'parameters file {path} does not exist')
        except IsADirectoryError:
            problems.append(f'parameters file {path} is a directory, expected a YAML file')
        except (OSError, UnicodeDecodeError) as err:
            problems.append(f'parameters file {path} cannot be read: {err}')
        except yaml.YAMLError as err:
            problems.append(f'parameters file {path} is not valid YAML: '
                            f'{" ".join(str(err).split())}')
    return problems


def main(args: Sequence[str] | None = None) -> int:
    """Run the node; return 0, or 2 on a configuration error (one log line, no traceback)."""
    logger = rclpy.logging.get_logger(NODE_NAME)
    problems = check_params_files(sys.argv if args is None else args)
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
