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


def test_node_with_augmented_file_reproduces_predict(tmp_path):
    sim = simulate(SimConfig(duration_s=12.0, seed=5))
    wheels = sim.wheels
    path = write_params_file(tmp_path / 'augmented.yaml', AUGMENTED, {'source': 'test'})
    config = OdometryConfig.from_file(path)
    assert config.bound_model().output_offset_ns == 80_000_000
    expected = Odometer.from_config(config).predict(wheels)
    result = replay_through_node(wheels, params_file=path)
    assert len(result) == len(wheels)
    # published stamps carry the time offset: sample stamp + 80 ms
    assert np.array_equal(result.t_ns, wheels.t_ns + 80_000_000)
    assert np.array_equal(result.t_ns, expected.t_ns)
    np.testing.assert_allclose(result.poses, expected.poses, atol=1e-9)
    np.testing.assert_allclose(result.vx, expected.twists[:, 0], atol=1e-12)
    np.testing.assert_allclose(result.vy, expected.twists[:, 1], atol=1e-12)
    np.testing.assert_allclose(result.wz, expected.twists[:, 2], atol=1e-12)
    # the state matters: the base model alone goes elsewhere
    base = predict_wheels(wheels, config.bound_model('edd_symmetric'))
    assert np.hypot(*(base.poses[-1, :2] - result.poses[-1, :2])) > 0.05


CALIBRATED = {
    'wheel_radius': 0.1651, 'track_width': 0.555, 'robot': 'sim_husky', 'model': 'edd_symmetric',
    'models.edd_symmetric.alpha': 0.9, 'models.edd_symmetric.b_hat': 0.85,
    'models.edd_symmetric.noise.calibrated': True,
    'models.edd_symmetric.noise.var_x_per_m': 4e-4, 'models.edd_symmetric.noise.var_y_per_m': 1e-4,
    'models.edd_symmetric.noise.var_yaw_per_m': 2e-5,
    'models.edd_symmetric.noise.var_yaw_per_rad': 5e-4,
    'models.edd_symmetric.noise.var_x_const': 3e-4, 'models.edd_symmetric.noise.var_y_const': 1e-4,
    'models.edd_symmetric.noise.var_yaw_const': 2e-4,
    'models.edd_symmetric.parameter_covariance': [4e-4, 1e-4, 1e-4, 9e-4],
}


@pytest.mark.parametrize('use', [True, False])
def test_node_publishes_the_covariance_of_predict_bit_for_bit(tmp_path, use):
    """Length-independent noise and parameter covariance: the node == Odometer.predict."""
    sim = simulate(SimConfig(duration_s=8.0, seed=7))
    wheels = sim.wheels
    flat = dict(CALIBRATED, use_parameter_covariance=use)
    path = write_params_file(tmp_path / 'calibrated.yaml', flat, {'source': 'test'})
    config = OdometryConfig.from_file(path)
    assert (config.active_parameter_uncertainty is not None) == use
    expected = Odometer.from_config(config).predict(wheels)
    result = replay_through_node(wheels, params_file=path)
    assert len(result) == len(wheels)
    np.testing.assert_array_equal(result.pose_cov, expected.pose_covariances)
    np.testing.assert_allclose(result.poses, expected.poses, atol=1e-9)
    # the parameter term grows with the distance: far larger than the noise alone at the end
    off = Odometer.from_config(OdometryConfig.from_file(
        path, overrides={'use_parameter_covariance': False})).predict(wheels)
    ratio = expected.pose_covariances[-1, 0, 0] / off.pose_covariances[-1, 0, 0]
    assert ratio > 1.5 if use else ratio == 1.0
