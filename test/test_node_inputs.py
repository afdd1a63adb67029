"""The real node: a controller's odometry as input; ~/reset and ~/set_pose keep the baseline.

Fault rows N80-N82 of docs/fault-matrix.md.
"""

import math

from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from node_harness import NS_PER_S, RELIABLE, wall_ns
import numpy as np
import pytest
from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.controller import ControllerGeometry
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.errors import ConfigError
from skidkin_ros.node.conversions import ns_to_stamp
from std_srvs.srv import Trigger

pytestmark = pytest.mark.ros

UNIT = {'model': 'ideal_dd', 'wheel_radius': 1.0, 'track_width': 1.0,
        'models.ideal_dd.noise.calibrated': True}
CONTROLLER = ControllerGeometry(0.16, 0.5, 1.03, 0.97, 1.2)
DT = 100_000_000


def _set_pose(rig, x, y, yaw, variance=0.0):
    msg = PoseWithCovarianceStamped()
    msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
    msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    msg.pose.covariance[0] = variance
    before = rig.node.counters['set_pose']
    rig.wait_matched(rig.set_pose_pub)
    rig.set_pose_pub.publish(msg)
    rig.spin_until(lambda: rig.node.counters['set_pose'] > before, what='set_pose')


def _reset(rig):
    assert rig.reset_client.wait_for_service(timeout_sec=5.0)
    future = rig.reset_client.call_async(Trigger.Request())
    rig.spin_until(future.done, what='reset response')
    assert future.result().success


def test_n81_set_pose_keeps_the_integration_baseline(make_rig):
    """Baseline, set_pose (5, -2, pi/2), 10 x (1, 1) rad/s 0.1 s apart: the full metre."""
    rig = make_rig(UNIT)
    t0 = wall_ns() - 5 * NS_PER_S
    rig.send_joint(t0, 1.0, 1.0)
    _set_pose(rig, 5.0, -2.0, math.pi / 2, variance=0.25)
    for k in range(1, 11):
        rig.send_joint(t0 + k * DT, 1.0, 1.0)
    rig.drain()
    # diff_drive_controller keeps its wheel baseline across a set or a reset: (5.0, -1.0).
    assert rig.node.pose == pytest.approx([5.0, -1.0, math.pi / 2], abs=1e-9)
    # The set covariance is kept and grows from there (x variance 0.25 m^2 at least).
    assert rig.odom[-1].pose.covariance[0] >= 0.25
    # ~/reset likewise: the next interval's travel counts from the origin.
    _reset(rig)
    for k in range(11, 16):
        rig.send_joint(t0 + k * DT, 1.0, 1.0)
    rig.drain()
    assert rig.node.pose == pytest.approx([0.5, 0.0, 0.0], abs=1e-9)
    assert rig.odom[-1].pose.covariance[0] < 0.25  # restarted from (almost) zero


def test_n81_a_clock_change_still_forgets_the_baseline(make_rig):
    rig = make_rig(UNIT)
    t0 = wall_ns() - 5 * NS_PER_S
    rig.send_joint(t0, 1.0, 1.0)
    with rig.node._lock:
        rig.node._odometer.clock_changed()  # what the node does on a /clock jump (N12)
    for k in range(1, 11):
        rig.send_joint(t0 + k * DT, 1.0, 1.0)
    rig.drain()
    assert rig.node.pose[0] == pytest.approx(0.9, abs=1e-9)  # the stamps before mean nothing


def _odometry(t_ns, v, w):
    msg = Odometry()
    msg.header.stamp = ns_to_stamp(t_ns)
    msg.header.frame_id, msg.child_frame_id = 'odom', 'base_link'
    msg.twist.twist.linear.x, msg.twist.twist.angular.z = float(v), float(w)
    return msg


def test_n80_the_node_runs_on_a_controllers_odometry_and_refuses_a_nan_twist(make_rig):
    overrides = {'input': 'odometry', 'model': 'edd_symmetric', **CONTROLLER.as_values()}
    rig = make_rig(overrides)
    publisher = rig.driver.create_publisher(Odometry, 'wheel_odom', RELIABLE)
    t0 = wall_ns() - 5 * NS_PER_S
    rng = np.random.default_rng(3)
    twists = [(t0 + k * 20_000_000, *rng.uniform([-0.5, -1.0], [1.0, 1.0])) for k in range(30)]
    bad = (t0 + 15 * 20_000_000 + 10_000_000, math.nan, 0.2)
    for k, twist in enumerate(twists):
        rig.send(_odometry(*twist), publisher)
        if k == 15:
            rig.send(_odometry(*bad), publisher)
    rig.drain()
    assert rig.node.counters['non_finite_twist'] == 1
    assert 'not finite' in rig.node.last_warnings['non_finite_twist']
    status = {kv.key: kv.value for kv in rig.node.diagnostic_status().values}
    assert status['count.non_finite_twist'] == '1'
    assert len(rig.odom) == 30
    # The same twists through the one rule offline: the node's pose, bit for bit.
    config = OdometryConfig.from_flat(overrides)
    speeds = [CONTROLLER.wheel_speeds(v, w) for _, v, w in twists]
    wheels = WheelSamples([t for t, _, _ in twists], [s[0] for s in speeds],
                          [s[1] for s in speeds])
    offline = Odometer.from_config(config).predict(wheels)
    np.testing.assert_array_equal(rig.node.pose, offline.poses[-1])


def test_n82_the_odometry_input_without_the_controller_geometry_is_refused_at_start(make_rig):
    with pytest.raises(ConfigError, match='controller.wheel_radius'):
        make_rig({'input': 'odometry'})
