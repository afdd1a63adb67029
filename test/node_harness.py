"""Test rig for the odometry node: the real OdomNode, a driver node and an executor in-process."""

from __future__ import annotations

import itertools
import os
import time
from typing import Any, Callable, Mapping, Sequence

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from skidkin_ros.node.conversions import ns_to_stamp
from skidkin_ros.node.odom_node import OdomNode
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

LEFT = ['front_left_wheel_joint', 'rear_left_wheel_joint']
RIGHT = ['front_right_wheel_joint', 'rear_right_wheel_joint']
NS_PER_S = 1_000_000_000
RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
_count = itertools.count()


def wall_ns() -> int:
    """Return the system clock in ns (the node clock without use_sim_time)."""
    return time.time_ns()


class NodeRig:
    """One OdomNode under test with publishers for every input and collectors for its outputs."""

    def __init__(self, overrides: Mapping[str, Any] | None = None,
                 params_file: str | None = None) -> None:
        self.context = Context()
        rclpy.init(args=[], context=self.context)
        self.namespace = f'/t{os.getpid()}_{next(_count)}'
        cli_args = ['--ros-args', '--params-file', str(params_file)] if params_file else None
        try:
            self.node = OdomNode(
                context=self.context, namespace=self.namespace, cli_args=cli_args,
                use_global_arguments=False,
                parameter_overrides=[Parameter(k, value=v) for k, v in (overrides or {}).items()])
        except BaseException:
            self.context.try_shutdown()
            raise
        self.driver = rclpy.create_node('driver', namespace=self.namespace,
                                        context=self.context, use_global_arguments=False)
        d = self.driver
        self.joint_pub = d.create_publisher(JointState, 'joint_states', RELIABLE)
        self.left_pub = d.create_publisher(Float64, 'wheel/left/velocity', RELIABLE)
        self.right_pub = d.create_publisher(Float64, 'wheel/right/velocity', RELIABLE)
        self.set_pose_pub = d.create_publisher(PoseWithCovarianceStamped, 'odom_node/set_pose',
                                               RELIABLE)
        self.clock_pub = d.create_publisher(Clock, '/clock', RELIABLE)
        self.reset_client = d.create_client(Trigger, 'odom_node/reset')
        self.odom: list[Odometry] = []
        self.diagnostics: list[DiagnosticArray] = []
        d.create_subscription(Odometry, 'odom', self.odom.append, RELIABLE)
        d.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, RELIABLE)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.executor.add_node(d)
        self.joint_names = list(self.node.config['left_wheel_joints'] +
                                self.node.config['right_wheel_joints'])
        self.spin_until(lambda: self.node._output.publisher.get_subscription_count() > 0,
                        what='odom subscription to match')

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        if any(status.name.startswith(self.node.get_fully_qualified_name())
               for status in msg.status):
            self.diagnostics.append(msg)

    def spin_until(self, done: Callable[[], bool], timeout_s: float = 5.0,
                   what: str = 'condition') -> None:
        deadline = time.monotonic() + timeout_s
        while not done():
            assert time.monotonic() < deadline, f'timed out waiting for {what}'
            self.executor.spin_once(timeout_sec=0.01)

    def spin_for(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)

    def wait_matched(self, publisher: Any) -> None:
        self.spin_until(lambda: publisher.get_subscription_count() > 0, what='publisher match')

    def joint_state(self, t_ns: int, omega_l: float, omega_r: float,
                    names: Sequence[str] | None = None,
                    velocity: Sequence[float] | None = None) -> JointState:
        msg = JointState()
        msg.header.stamp = ns_to_stamp(t_ns)
        msg.name = list(names if names is not None else self.joint_names)
        if velocity is None:
            n_left = len(self.node.config['left_wheel_joints'])
            n_right = len(self.node.config['right_wheel_joints'])
            velocity = [omega_l] * n_left + [omega_r] * n_right
        msg.velocity = [float(v) for v in velocity]
        return msg

    def send(self, msg: Any, publisher: Any = None) -> None:
        """Publish one input message and spin until the node has taken it."""
        publisher = publisher or self.joint_pub
        self.wait_matched(publisher)
        before = self.node.counters['received']
        publisher.publish(msg)
        self.spin_until(lambda: self.node.counters['received'] > before, what='node to take it')

    def send_joint(self, t_ns: int, omega_l: float, omega_r: float, **kwargs: Any) -> None:
        self.send(self.joint_state(t_ns, omega_l, omega_r, **kwargs))

    def drain(self) -> None:
        """Spin until every published odometry message has arrived."""
        self.spin_until(lambda: len(self.odom) >= self.node.counters['published'],
                        what='odometry')

    def publish_clock(self, t_ns: int) -> None:
        self.wait_matched(self.clock_pub)
        msg = Clock()
        msg.clock = ns_to_stamp(t_ns)
        self.clock_pub.publish(msg)
        self.spin_until(lambda: self.node.get_clock().now().nanoseconds == t_ns,
                        what='/clock to reach the node')

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.driver.destroy_node()
        self.context.try_shutdown()


def best_effort_publisher(rig: NodeRig) -> Any:
    """Return a best-effort JointState publisher (like many drivers) on the rig's topic."""
    return rig.driver.create_publisher(JointState, 'joint_states', qos_profile_sensor_data)


def assert_online_replay_matches(result: Any, expected: Any, samples: Any) -> None:
    """Assert a replay through the node equals ``skidkin predict``'s, pose and covariance.

    One message per wheel sample; x and y bit for bit, the yaw to the rounding of the published
    quaternion (1e-12), the published pose covariance bit for bit.
    """
    assert len(result) == len(samples)
    assert np.array_equal(result.poses[:, :2], expected.poses[:, :2])
    np.testing.assert_allclose(result.poses[:, 2], expected.poses[:, 2], rtol=0, atol=1e-12)
    assert np.array_equal(result.pose_cov, expected.pose_covariances)


def assert_replay_matches(result: Any, expected: Any) -> None:
    """Assert a replay through the node equals ``skidkin predict``'s prediction.

    The stamps and the twists bit for bit; the poses to the rounding of the published
    quaternion (1e-12).
    """
    assert np.array_equal(result.t_ns, expected.t_ns)
    for published, c in ((result.vx, 0), (result.vy, 1), (result.wz, 2)):
        assert np.array_equal(published, expected.twists[:, c])
    np.testing.assert_allclose(result.poses, expected.poses, rtol=0, atol=1e-12)
