"""The real node runs an augmented parameters file exactly like the odometer offline."""

import numpy as np
import pytest
from skidkin_ros.core.odometry.config import OdometryConfig, write_params_file
from skidkin_ros.core.odometry.odometer import Odometer, predict_wheels
from skidkin_ros.node.replay import replay_through_node
from skidkin_ros.sim.simulate import SimConfig, simulate

pytestmark = pytest.mark.ros

AUGMENTED = {
    'wheel_radius': 0.1651, 'track_width': 0.555, 'robot': 'sim_husky',
    'model': 'augmented', 'augmented.base': 'edd_symmetric',
    'augmented.extensions': 'lateral_skid, first_order_lag, time_offset, terrain_regime',
    'models.edd_symmetric.alpha': 0.9, 'models.edd_symmetric.b_hat': 0.85,
    'augmented.lateral_skid.k': 0.06, 'augmented.first_order_lag.tau_s': 0.2,
    'augmented.time_offset.offset_s': 0.08, 'augmented.terrain_regime.k': 0.2,
    'augmented.terrain_regime.switch_s': 6.0,
}


@pytest.mark.parametrize('interval', ['ending', 'starting', 'midpoint'])
def test_node_with_augmented_file_reproduces_predict(tmp_path, interval):
    sim = simulate(SimConfig(duration_s=12.0, seed=5))
    wheels = sim.wheels
    path = write_params_file(tmp_path / 'augmented.yaml', {**AUGMENTED, 'interval': interval},
                             {'source': 'test'})
    config = OdometryConfig.from_file(path)
    assert config.bound_model().output_offset_ns == 80_000_000
    assert config['interval'] == interval
    expected = Odometer.from_config(config).predict(wheels)
    result = replay_through_node(wheels, params_file=path)
    assert len(result) == len(wheels)
    # published stamps carry the time offset: sample stamp + 80 ms
    assert np.array_equal(result.t_ns, wheels.t_ns + 80_000_000)
    assert np.array_equal(result.t_ns, expected.t_ns)
    # bit for bit: the node and predict run the same odometer on the same floats (the yaw goes
    # through a quaternion on the wire)
    assert np.array_equal(result.poses[:, :2], expected.poses[:, :2])
    np.testing.assert_allclose(result.poses[:, 2], expected.poses[:, 2], rtol=0, atol=1e-12)
    assert np.array_equal(np.stack([result.vx, result.vy, result.wz], axis=-1), expected.twists)
    # the state matters: the base model alone goes elsewhere
    base = predict_wheels(wheels, config.bound_model('edd_symmetric'), interval=interval)
    assert np.hypot(*(base.poses[-1, :2] - result.poses[-1, :2])) > 0.05
    # and so does the convention: another one goes elsewhere too
    other = 'starting' if interval != 'starting' else 'ending'
    moved = Odometer.from_config(OdometryConfig.from_flat({**config.values, 'interval': other}))
    assert np.abs(moved.predict(wheels).poses[-1] - result.poses[-1]).max() > 1e-4


def test_node_runs_a_calibrated_file_without_interval_as_starting(tmp_path):
    # a file written by calibrate before the convention existed: provenance, no interval
    sim = simulate(SimConfig(duration_s=6.0, seed=6))
    flat = {k: v for k, v in AUGMENTED.items() if not k.startswith('augmented')}
    path = write_params_file(tmp_path / 'old.yaml', {**flat, 'model': 'edd_symmetric'},
                             {'tool': 'skidkin_ros 0.9'})
    assert 'interval' not in path.read_text()
    config = OdometryConfig.from_file(path)
    assert config['interval'] == 'starting'
    result = replay_through_node(sim.wheels, params_file=path)
    expected = Odometer.from_config(config).predict(sim.wheels)
    assert np.array_equal(result.poses[:, :2], expected.poses[:, :2])
    ending = predict_wheels(sim.wheels, config.bound_model(), interval='ending')
    assert np.abs(ending.poses[-1, :2] - result.poses[-1, :2]).max() > 1e-4
