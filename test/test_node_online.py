"""The real node learning online from reference/odom: as predict does, and never stopped by it."""

import math

from nav_msgs.msg import Odometry
from node_harness import assert_online_replay_matches, NodeRig, RELIABLE, wall_ns
import numpy as np
import pytest
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.core.odometry.config import OdometryConfig, write_params_file
from skidkin_ros.core.online import online_odometer
from skidkin_ros.core.rotation import quaternion_to_yaw, yaw_to_quaternion
from skidkin_ros.node.conversions import ns_to_stamp
from skidkin_ros.node.replay import replay_through_node
from skidkin_ros.sim.effects import make_effect
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate
from std_srvs.srv import Trigger

pytestmark = pytest.mark.ros

FILE = {'model': 'edd_asymmetric', 'robot': 'sim_husky',
        **{f'models.edd_asymmetric.{k}': v for k, v in DEFAULT_TRUE_PARAMS.items()},
        'models.edd_asymmetric.noise.calibrated': True, 'online.enabled': True}


def test_node_learning_online_reproduces_predict(tmp_path):
    effect = make_effect('terrain_regime', 0.25, mode='time', switch_frac=0.4, yaw=0.1)
    sim = simulate(SimConfig(duration_s=40.0, seed=3, effects=(effect,)))
    path = write_params_file(tmp_path / 'online.yaml', FILE, {'source': 'test'})
    config = OdometryConfig.from_file(path)
    reference = sim.truth_at(np.arange(sim.start_ns, sim.end_ns, 100_000_000))
    # the yaw reaches the node through a quaternion: predict gets the same numbers
    wire_yaw = [quaternion_to_yaw(*yaw_to_quaternion(float(v))) for v in reference.yaw]
    odometer = online_odometer(config)
    expected = odometer.predict(sim.wheels, reference=PoseTrack(
        reference.t_ns, reference.x, reference.y, np.array(wire_yaw)))
    assert odometer.counters['online_segments'] >= 8
    result = replay_through_node(sim.wheels, params_file=path, reference=reference,
                                 timeout_s=120.0)
    assert_online_replay_matches(result, expected, sim.wheels)
    # and the parameters learned moved the odometry away from the file's
    fixed = online_odometer(OdometryConfig.from_flat({**config.values, 'online.enabled': False}))
    assert np.abs(fixed.predict(sim.wheels).poses[-1, :2] - result.poses[-1, :2]).max() > 0.05
    for cause in ('online_segments', 'online_change', 'reference_accepted'):
        assert result.counters.get(cause, 0) == odometer.counters[cause]


def _reference_msg(t_ns, x, y, yaw, child='base_link'):
    msg = Odometry()
    msg.header.stamp = ns_to_stamp(t_ns)
    msg.header.frame_id = 'odom_lidar'
    msg.child_frame_id = child
    msg.pose.pose.position.x = float(x)
    msg.pose.pose.position.y = float(y)
    qx, qy, qz, qw = yaw_to_quaternion(float(yaw)) if math.isfinite(yaw) else (0, 0, yaw, 1.0)
    msg.pose.pose.orientation.z = float(qz)
    msg.pose.pose.orientation.w = float(qw)
    return msg


def test_bad_reference_never_stops_the_odometry_and_save_calibration(tmp_path):
    target = tmp_path / 'learned.yaml'
    rig = NodeRig({**FILE, 'online.save_path': str(target),
                   'online.reference_child_frame_id': 'base_link'})
    try:
        ref_pub = rig.driver.create_publisher(Odometry, 'reference/odom', RELIABLE)
        rig.wait_matched(ref_pub)
        client = rig.driver.create_client(Trigger, 'odom_node/save_calibration')

        def send_reference(msg):
            before = rig.node.counters['reference_received']
            ref_pub.publish(msg)
            rig.spin_until(lambda: rig.node.counters['reference_received'] > before,
                           what='reference pose')
        t0 = wall_ns() - 30 * 1_000_000_000
        speed = 0.5 * 0.1651 * 0.9   # both wheels at 0.5 rad/s: straight at ~0.074 m/s
        for i in range(200):
            t = t0 + i * 50_000_000
            rig.send_joint(t, 0.5, 0.5)
            if i % 2 == 0:
                x = speed * i * 0.05
                send_reference(_reference_msg(t, x, 0.0, 0.0))
                if i % 20 == 10:
                    send_reference(_reference_msg(t + 1, math.nan, 0.0, 0.0))   # NaN
                    send_reference(_reference_msg(t - 10_000_000, x, 0.0, 0.0))  # back
                    send_reference(_reference_msg(t + 1_000_000, x, 0.0, 0.0))   # 1 kHz
                    send_reference(_reference_msg(t + 2_000_000, x + 5, 0.0, 0.0,
                                                  'camera'))                    # frame
        rig.drain()
        counters = rig.node.counters
        for cause in ('reference_non_finite', 'reference_older', 'reference_rate_limited',
                      'reference_frame'):
            assert counters[cause] >= 9, cause
        assert counters['published'] == 200 == len(rig.odom)
        assert all(math.isfinite(m.pose.pose.position.x) for m in rig.odom)
        assert all(np.all(np.isfinite(m.pose.covariance)) for m in rig.odom)
        status = rig.node.diagnostic_status()
        values = {kv.key: kv.value for kv in status.values}
        assert values['online.state'] in ('learning', 'adapting')
        assert 'online.alpha_l.sigma' in values and 'count.reference_frame' in values
        # the reference's noise in use (configured until measured)
        assert float(values['online.reference_sigma_xy']) > 0.0
        assert float(values['online.reference_sigma_yaw']) > 0.0
        assert client.wait_for_service(timeout_sec=5.0)
        for expect in (True, False):   # the second call finds the file: never overwritten
            future = client.call_async(Trigger.Request())
            rig.spin_until(future.done, what='save_calibration')
            assert future.result().success is expect, future.result().message
        assert 'never overwritten' in future.result().message
        loaded = OdometryConfig.from_file(target)
        assert loaded.online.enabled and 'online calibration' in target.read_text()
    finally:
        rig.close()


def test_node_takes_a_late_references_delay_as_predict_does(tmp_path):
    # the reference stamped 0.4 s late, online.time_offset left at 0: the node measures the
    # delay by the offline lag rule, takes it in force, and agrees with predict bit for bit
    sim = simulate(SimConfig(duration_s=40.0, seed=4))
    path = write_params_file(tmp_path / 'online.yaml', {**FILE, 'online.delay_tolerance': 0.06},
                             {'source': 'test'})
    config = OdometryConfig.from_file(path)
    t = np.arange(sim.start_ns + 1_000_000_000, sim.end_ns - 1_000_000_000, 100_000_000)
    truth = sim.truth_at(t)
    late = PoseTrack(t + 400_000_000, truth.x, truth.y, truth.yaw)
    wire_yaw = [quaternion_to_yaw(*yaw_to_quaternion(float(v))) for v in late.yaw]
    odometer = online_odometer(config)
    expected = odometer.predict(sim.wheels, reference=PoseTrack(late.t_ns, late.x, late.y,
                                                                np.array(wire_yaw)))
    assert odometer.counters['online_delay_corrected'] == 1
    assert odometer.learner.summary()['measured_delay'] == pytest.approx(0.4, abs=0.1)
    result = replay_through_node(sim.wheels, params_file=path, reference=late, timeout_s=120.0)
    assert np.array_equal(result.poses[:, :2], expected.poses[:, :2])
    np.testing.assert_allclose(result.poses[:, 2], expected.poses[:, 2], rtol=0, atol=1e-12)
    assert np.array_equal(result.pose_cov, expected.pose_covariances)
    for cause in ('online_delay_corrected', 'online_segments', 'reference_accepted'):
        assert result.counters.get(cause, 0) == odometer.counters[cause]
