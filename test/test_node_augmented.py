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


# Per-component lag, acceleration slip and a sparse correction with derivative terms: the node
# must reproduce predict exactly, the rate of change included.
RATE_DEPENDENT = dict(AUGMENTED, **{
    'augmented.extensions': 'component_lags, acceleration_slip, sparse_correction',
    'augmented.component_lags.tau_v_s': 0.15, 'augmented.component_lags.tau_w_s': 0.08,
    'augmented.acceleration_slip.tau_s': 0.1, 'augmented.sparse_correction.vx_dv_up': -0.05,
    'augmented.sparse_correction.wz_dw': 0.02,
})


def test_node_runs_rate_dependent_extensions_bit_for_bit(tmp_path):
    wheels = simulate(SimConfig(duration_s=12.0, seed=6)).wheels
    path = write_params_file(tmp_path / 'rates.yaml', RATE_DEPENDENT, {'source': 'test'})
    expected = Odometer.from_config(OdometryConfig.from_file(path)).predict(wheels)
    result = replay_through_node(wheels, params_file=path)
    assert np.array_equal(result.t_ns, expected.t_ns)
    # twists bit for bit; poses to the rounding of the published quaternion
    for published, c in ((result.vx, 0), (result.vy, 1), (result.wz, 2)):
        assert np.array_equal(published, expected.twists[:, c])
    np.testing.assert_allclose(result.poses, expected.poses, rtol=0, atol=1e-12)
    # the rate terms matter: without them the forward speed differs
    plain = dict(RATE_DEPENDENT, **{'augmented.extensions': 'component_lags'})
    other = Odometer.from_config(OdometryConfig.from_file(write_params_file(
        tmp_path / 'plain.yaml', plain, {'source': 'test'}))).predict(wheels)
    assert np.abs(other.twists[:, 0] - expected.twists[:, 0]).max() > 0.01
