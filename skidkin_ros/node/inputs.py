"""The node's input callbacks: one per wheel input, the gyro and the reference.

The inputs are JointState, two Float64 wheel topics, a controller's Odometry, the gyro and the
online-calibration reference. Each takes the node's lock, turns the message into the odometer's
call and publishes what comes back; the rules live in the core.
"""

from __future__ import annotations

import math
import time

from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Imu, JointState
from skidkin_ros.core.odometry.wheels import (check_position_count, check_velocity_count,
                                              DuplicateJointError, joint_indices,
                                              MissingJointError, positions_at, repeated_names,
                                              speeds_at)
from skidkin_ros.core.rotation import quaternion_to_yaw
from skidkin_ros.node.callbacks import guarded as _guarded
from skidkin_ros.node.conversions import stamp_to_ns
from skidkin_ros.node.wire import JointStateFields, WireFormatError
from std_msgs.msg import Float64

__all__ = ['InputCallbacks']


class InputCallbacks:
    """The input half of :class:`~skidkin_ros.node.odom_node.OdomNode` (a mixin of it)."""

    @_guarded
    def _on_joint_state(self, msg: bytes | JointState) -> None:
        """Take a JointState, serialized (the subscription's form) or as a message."""
        with self._lock:
            self.counters['received'] += 1
            fields = self._joint_state_fields(msg)
            if fields is None:
                return
            names, velocity, position = fields.names, fields.velocity, fields.position
            has_position = (self._config['wheel_signal'] != 'velocity'
                            and check_position_count(len(names), len(position)))  # may raise
            if not (has_position and self._config['wheel_signal'] == 'position' and not velocity):
                check_velocity_count(len(names), len(velocity))  # raises: reported by _guarded
            if names != self._joint_names:
                config = self._config
                try:
                    self._joint_index = joint_indices(names, config['left_wheel_joints'],
                                                      config['right_wheel_joints'])
                except MissingJointError as err:
                    self._reject('missing_joint', str(err))
                    return
                except DuplicateJointError as err:
                    self._reject('duplicate_joint', str(err))
                    return
                self._joint_names = names
                repeated = repeated_names(names)
                if repeated:  # once per name list: these joints are not the wheels
                    self._warn('repeated_joint', f'JointState lists joint(s) {repeated} more '
                               'than once; they are not wheel joints, odometry is unaffected; '
                               'fix the driver so that each joint is listed once')
            omega_l, omega_r = (speeds_at(velocity, *self._joint_index) if velocity
                                else (math.nan, math.nan))
            positions = positions_at(position, *self._joint_index) if has_position else None
            now_ns = self._clock_now_ns()
            if now_ns is None:
                return
            estimate = self._odometer.joint_sample(fields.stamp_ns, omega_l, omega_r, now_ns,
                                                   positions)
            if estimate is not None:
                self._publish(estimate)

    def _joint_state_fields(self, msg: bytes | JointState) -> JointStateFields | None:
        """Return the fields the node uses, or None (counted, reported) if the message is bad.

        Serialized input is read by node.wire; what it does not read is deserialized by rclpy
        (never dropped for the fast path's sake), and what rclpy refuses too is dropped.
        """
        if isinstance(msg, bytes):
            try:
                return self._joint_reader.read(msg)
            except WireFormatError as err:
                reason = str(err)
            try:
                msg = deserialize_message(msg, JointState)
            except RuntimeError as err:  # rclpy's RMWError: the message does not deserialize
                self._reject('malformed_message',
                             f'JointState dropped: it does not deserialize ({reason}; rclpy: '
                             f'{" ".join(str(err).split())})')
                return None
            self.counters['read_by_rclpy'] += 1
            if not self._rclpy_read_logged:
                self._rclpy_read_logged = True
                self.get_logger().info(f'a JointState was read by rclpy instead of the fast '
                                       f'reader ({reason}); such messages cost more CPU, '
                                       'counted as read_by_rclpy in /diagnostics')
        return JointStateFields(stamp_to_ns(msg.header.stamp), tuple(msg.name),
                                tuple(msg.position), tuple(msg.velocity))

    @_guarded
    def _on_imu(self, msg: Imu) -> None:
        """Take a gyro sample: the yaw rate angular_velocity.z, on header.stamp."""
        with self._lock:
            self.counters['imu_received'] += 1
            if msg.angular_velocity_covariance[0] == -1.0:
                self._reject('imu_no_rate', 'Imu message has angular_velocity_covariance[0] = '
                             '-1 ("no angular velocity data"): not used')
                return
            now_ns = self._clock_now_ns()
            if now_ns is None:
                return
            for estimate in self._odometer.imu_sample(stamp_to_ns(msg.header.stamp),
                                                      msg.angular_velocity.z, now_ns):
                self._publish(estimate)

    @_guarded
    def _on_wheel_odometry(self, msg: Odometry) -> None:
        """Take a drive controller's Odometry: its twist, on header.stamp."""
        with self._lock:
            self.counters['received'] += 1
            now_ns = self._clock_now_ns()
            if now_ns is None:
                return
            twist = msg.twist.twist
            estimate = self._odometer.twist_sample(stamp_to_ns(msg.header.stamp),
                                                   twist.linear.x, twist.angular.z, now_ns)
            if estimate is not None:
                self._publish(estimate)

    @_guarded
    def _on_reference(self, msg: Odometry) -> None:
        """Take a reference pose (online calibration): header.stamp, pose.pose, its frames.

        And pose.covariance's yaw variance: a GNSS converter's huge one says the heading is not
        measured (online.reference_heading auto).
        """
        with self._lock:
            self.counters['reference_received'] += 1
            pose = msg.pose.pose
            q = pose.orientation
            yaw = quaternion_to_yaw(q.x, q.y, q.z, q.w)
            self._odometer.reference_sample(stamp_to_ns(msg.header.stamp), pose.position.x,
                                            pose.position.y, yaw, msg.header.frame_id,
                                            msg.child_frame_id, msg.pose.covariance[35])

    @_guarded
    def _on_left_wheel(self, msg: Float64) -> None:
        self._on_wheel('left', msg.data)

    @_guarded
    def _on_right_wheel(self, msg: Float64) -> None:
        self._on_wheel('right', msg.data)

    def _on_wheel(self, side: str, omega_rad_s: float) -> None:
        """Hand one side's speed, stamped with the node clock, to the odometer's pairing (N9)."""
        with self._lock:
            self.counters['received'] += 1
            now_ns = self._clock_now_ns()
            if now_ns is None:
                return
            self._side_seen_mono_ns[side] = time.monotonic_ns()
            estimate = self._odometer.wheel_sample(side, omega_rad_s, now_ns)
            if estimate is not None:
                self._publish(estimate)
