"""What the node publishes for each estimate: nav_msgs/Odometry on ``odom`` and, if asked, TF.

The Odometry goes out pre-serialized (:mod:`skidkin_ros.node.wire`) when the serializer agrees
with the middleware for the frames in force, else as a message object (slower, same content).
The odom -> base transform needs tf2_ros, which is optional: without it the node says so once
and publishes odometry as usual.
"""

from __future__ import annotations

from typing import Any, Sequence

from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
import numpy as np
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.serialization import deserialize_message
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.odometer import Estimate
from skidkin_ros.core.rotation import yaw_to_quaternion
from skidkin_ros.core.timeunits import NS_PER_S
from skidkin_ros.node.conversions import ns_to_stamp
from skidkin_ros.node.wire import OdometryWriter

__all__ = ['OdometryOutput']


class OdometryOutput:
    """The ``odom`` publisher, its serializer and the optional TF broadcaster of one node."""

    def __init__(self, node: Node, qos: QoSProfile, publish_tf: bool) -> None:
        self._node = node
        self.publisher = node.create_publisher(
            Odometry, 'odom', qos, qos_overriding_options=QoSOverridingOptions
            .with_default_policies())
        self._msg = Odometry()
        # Serializer of the output for the frames in force (None: publish message objects).
        self.writer: OdometryWriter | None = None
        self.writer_frames: tuple[str, str] | None = None
        self._tf = self._make_tf_broadcaster(publish_tf)

    def configure(self, config: OdometryConfig) -> None:
        """Start the TF broadcaster when publish_tf is switched on at runtime."""
        if config['publish_tf'] and self._tf is None:
            self._tf = self._make_tf_broadcaster(True)

    def publish(self, estimate: Estimate, config: OdometryConfig) -> None:
        """Publish one estimate as Odometry (and TF when publish_tf)."""
        t_ns, (x, y, yaw), (vx, vy, w), pose_cov, twist_cov = estimate
        qx, qy, qz, qw = yaw_to_quaternion(yaw)
        writer = self._writer(config)
        if writer is not None:
            self.publisher.publish(writer.pack(t_ns, x, y, qz, qw, pose_cov, vx, vy, w,
                                               twist_cov))
        else:
            self.publisher.publish(self._odometry_msg(config, t_ns, x, y, qz, qw, pose_cov, vx,
                                                      vy, w, twist_cov))
        if self._tf is not None and config['publish_tf']:
            transform = TransformStamped()
            transform.header.stamp = ns_to_stamp(t_ns)
            transform.header.frame_id = config['odom_frame_id']
            transform.child_frame_id = config['base_frame_id']
            transform.transform.translation.x = x
            transform.transform.translation.y = y
            transform.transform.rotation.z = qz
            transform.transform.rotation.w = qw
            self._tf.sendTransform(transform)

    def _writer(self, config: OdometryConfig) -> OdometryWriter | None:
        """Return the serializer for the configured frames (None: publish messages instead)."""
        frames = (config['odom_frame_id'], config['base_frame_id'])
        if frames != self.writer_frames:
            writer: OdometryWriter | None = OdometryWriter(*frames)
            if not writer.agrees_with(deserialize_message, Odometry):
                self._node.get_logger().warning(
                    'the Odometry serializer disagrees with rclpy on this middleware: '
                    'publishing message objects instead (slower)')
                writer = None
            self.writer, self.writer_frames = writer, frames
        return self.writer

    def _odometry_msg(self, config: OdometryConfig, t_ns: int, x: float, y: float, qz: float,
                      qw: float, pose_cov: Sequence[float], vx: float, vy: float, w: float,
                      twist_cov: Sequence[float]) -> Odometry:
        msg = self._msg  # reused: publish() serializes it before returning
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
            self._node.get_logger().warning(
                'publish_tf is true but tf2_ros is not installed: the odom -> base transform is '
                'not broadcast (install ros-jazzy-tf2-ros); odometry is published as usual')
            return None
        return TransformBroadcaster(self._node)
