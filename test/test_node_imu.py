"""The real node with a gyro: same as predict, hostile Imu messages, stale gyro."""

import math

from node_harness import NS_PER_S, wall_ns
import numpy as np
import pytest
from sensor_msgs.msg import Imu
from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.core.odometry.config import OdometryConfig, write_params_file
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.node.conversions import ns_to_stamp
from skidkin_ros.node.replay import replay_through_node
from skidkin_ros.sim.simulate import SimConfig, simulate

pytestmark = pytest.mark.ros

PARAMS = {
    'wheel_radius': 0.1651, 'track_width': 0.555, 'robot': 'sim_husky',
    'model': 'edd_symmetric', 'models.edd_symmetric.alpha': 0.9,
    'models.edd_symmetric.b_hat': 0.85, 'models.edd_symmetric.noise.calibrated': True,
    'imu.max_wait': 0.5, 'imu.bias': 0.002, 'interval': 'ending',
}


@pytest.mark.parametrize('mode', ['fuse', 'adapt'])
def test_node_with_gyro_reproduces_predict(tmp_path, mode):
    sim = simulate(SimConfig(duration_s=4.0, seed=3))
    keep = sim.wheels.t_ns <= sim.imu.t_ns[-1] - 100_000_000   # the gyro outlasts the wheels
    wheels = WheelSamples(sim.wheels.t_ns[keep], sim.wheels.omega_l[keep],
                          sim.wheels.omega_r[keep])
    path = write_params_file(tmp_path / 'imu.yaml', {**PARAMS, 'imu.mode': mode},
                             {'source': 'test'})
    config = OdometryConfig.from_file(path)
    odometer = Odometer.from_config(config)
    expected = odometer.predict(wheels, imu=sim.imu)
    assert odometer.counters['imu_interval_covered'] > 0.9 * len(wheels)
    result = replay_through_node(wheels, params_file=path, imu=sim.imu)
    assert len(result) == len(wheels)
    assert np.array_equal(result.t_ns, expected.t_ns)
    np.testing.assert_allclose(result.poses, expected.poses, atol=1e-9)
    np.testing.assert_allclose(result.wz, expected.twists[:, 2], atol=1e-12)
    assert result.counters['imu_accepted'] == len(sim.imu.t_ns)
    # the gyro changed the odometry: wheels alone go elsewhere
    off = Odometer.from_config(OdometryConfig.from_file(path)).predict(wheels)
    plain = Odometer.from_config(OdometryConfig.from_flat({**PARAMS, 'imu.mode': 'off'}))
    assert np.array_equal(plain.predict(wheels).poses, off.poses)
    assert abs(off.poses[-1, 2] - result.poses[-1, 2]) > 1e-3


def test_replay_with_a_gyro_carries_the_encoder_positions(tmp_path):
    """N70: the replay harness with both a gyro and positions sends the positions too.

    The velocities sent are zero; with ``wheel_signal: position`` only the positions move the
    node (they were dropped when a gyro was replayed: every sample refused, no_position).
    """
    sim = simulate(SimConfig(duration_s=4.0, seed=3))
    keep = sim.wheels.t_ns <= sim.imu.t_ns[-1] - 100_000_000
    wheels = WheelSamples(sim.wheels.t_ns[keep], sim.wheels.omega_l[keep],
                          sim.wheels.omega_r[keep])
    still = WheelSamples(wheels.t_ns, np.zeros(len(wheels)), np.zeros(len(wheels)))
    positions = list(zip(sim.wheel_pos_l[keep].tolist(), sim.wheel_pos_r[keep].tolist()))
    flat = {**PARAMS, 'imu.mode': 'fuse', 'wheel_signal': 'position', 'interval': 'midpoint'}
    path = write_params_file(tmp_path / 'imu.yaml', flat, {'source': 'test'})
    result = replay_through_node(still, params_file=path, imu=sim.imu, positions=positions)
    assert result.counters.get('no_position', 0) == 0
    expected = Odometer.from_config(OdometryConfig.from_file(path)).predict(wheels, imu=sim.imu)
    assert np.hypot(*expected.poses[-1, :2]) > 0.3          # it drove
    # the first sample has no travel yet: the node's pose follows the true speeds' from there
    np.testing.assert_allclose(result.poses[-1, :2], expected.poses[-1, :2], atol=0.05)


def _yaw(msg):
    return 2 * math.atan2(msg.pose.pose.orientation.z, msg.pose.pose.orientation.w)


def _imu(t_ns, rate, orientation_unknown=False, rate_unknown=False):
    msg = Imu()
    msg.header.stamp = ns_to_stamp(t_ns)
    msg.angular_velocity.z = rate
    if orientation_unknown:
        msg.orientation_covariance[0] = -1.0
    if rate_unknown:
        msg.angular_velocity_covariance[0] = -1.0
    return msg


def test_hostile_imu_messages_are_counted_and_never_used(make_rig):
    rig = make_rig({'imu.mode': 'fuse', 'imu.time_offset': -0.05})
    pub = rig.driver.create_publisher(Imu, 'imu/data', 100)
    rig.spin_until(lambda: pub.get_subscription_count() > 0, what='imu subscription')
    start = wall_ns() - 5 * NS_PER_S
    gyro_dt, wheel_dt, rate = 10_000_000, 20_000_000, 0.3

    def send_imu(msg):
        before = rig.node.counters['imu_received']
        pub.publish(msg)
        rig.spin_until(lambda: rig.node.counters['imu_received'] > before, what='imu taken')

    hostile = {5: lambda t: _imu(0, rate),                               # zero stamp
               9: lambda t: _imu(start + 30 * NS_PER_S, rate),           # 25 s in the future
               13: lambda t: _imu(t + 1, math.nan),
               17: lambda t: _imu(t + 1, math.inf),
               21: lambda t: _imu(t + 1, 1e300),                          # huge: saturated
               25: lambda t: _imu(start, -50.0),                          # in the past: older
               29: lambda t: _imu(t + 1, 40.0, rate_unknown=True)}        # "no rate data"
    k = 0
    for i in range(40):                       # 0.8 s: wheels 50 Hz, gyro 100 Hz
        for _ in range(2):
            t = start + k * gyro_dt
            send_imu(_imu(t, rate, orientation_unknown=(k % 3 == 0)))
            if k in hostile:
                send_imu(hostile[k](t))
            k += 1
        rig.send_joint(start + i * wheel_dt, 2.0, 2.0)   # straight on the wheels
    rig.drain()
    counters = rig.node.counters
    assert counters['imu_bad_stamp'] == 1
    assert counters['imu_future_stamp'] == 1
    assert counters['imu_non_finite'] == 2
    assert counters['imu_saturated'] == 1
    assert counters['imu_older'] == 1
    assert counters['imu_no_rate'] == 1
    assert counters['published'] == 40            # every sample, none waits for ever
    covered = counters['imu_interval_covered']
    assert covered >= 30
    # the heading is the clean gyro's (0.3 rad/s) on the covered intervals, never the hostile
    yaw = _yaw(rig.odom[-1])
    integrated = (counters['imu_interval_covered']) * wheel_dt / NS_PER_S * rate
    assert yaw == pytest.approx(integrated, abs=1e-6)
    rig.spin_until(lambda: any(kv.key == 'imu.gain' for d in rig.diagnostics
                               for s in d.status for kv in s.values),
                   timeout_s=3.0, what='diagnostics with the gyro state')


def test_stale_gyro_never_stops_the_odometry(make_rig):
    rig = make_rig({'imu.mode': 'adapt'})
    start = wall_ns() - 5 * NS_PER_S
    for i in range(20):
        rig.send_joint(start + i * 20_000_000, 2.0, 3.0)
    rig.drain()
    assert rig.node.counters['published'] == 20
    assert rig.node.counters['imu_interval_stale'] == 19
    model = rig.node.config.bound_model()
    expected = model.scalar_twist(2.0, 3.0)[2] * 19 * 0.02
    yaw = _yaw(rig.odom[-1])
    assert yaw == pytest.approx(expected, rel=1e-9)


def test_imu_subscription_follows_the_mode(make_rig):
    from rclpy.parameter import Parameter
    rig = make_rig()
    topic = f'{rig.namespace}/imu/data'
    assert rig.node.count_publishers(topic) == 0 and rig.node._imu_sub is None
    rig.node.set_parameters([Parameter('imu.mode', value='fuse')])
    assert rig.node._imu_sub is not None
    result = rig.node.set_parameters([Parameter('imu.mode', value='gyro')])
    assert not result[0].successful and 'imu.mode' in result[0].reason
    rig.node.set_parameters([Parameter('imu.mode', value='off')])
    assert rig.node._imu_sub is None
