"""The real node runs an augmented parameters file exactly like the odometer offline."""

import math

from node_harness import assert_replay_matches
import numpy as np
import pytest
from skidkin_ros.adapters.bag_reader import open_recording
from skidkin_ros.adapters.bag_writer import BagWriter
from skidkin_ros.adapters.sim_writer import write_truth_csv
from skidkin_ros.adapters.sources import load_source, SourceOptions
from skidkin_ros.cli.common import input_parameters
from skidkin_ros.cli.main import main
from skidkin_ros.core.odometry.config import OdometryConfig, write_params_file
from skidkin_ros.core.odometry.odometer import Odometer, predict_wheels
from skidkin_ros.node.replay import replay_through_node
from skidkin_ros.sim.simulate import JOINT_NAMES, SimConfig, simulate

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


def _encoder_bag(path, sim, hostile):
    """Write a JointState bag of the simulated drive: velocities, wrapped positions, faults."""
    left, right = sim.wheel_pos_l.copy(), sim.wheel_pos_r.copy()
    if hostile:
        left[60:] -= 3.0  # the left counter steps back by 3 rad (60 rad/s in one sample)
    wrapped = [((a + math.pi) % (2 * math.pi) - math.pi, (b + math.pi) % (2 * math.pi) - math.pi)
               for a, b in zip(left, right)]
    if hostile:
        wrapped[30] = (math.nan, wrapped[30][1])
        for i in (90, 91, 120):
            wrapped[i] = None  # messages without positions
    with BagWriter(path) as writer:
        for i, t_ns in enumerate(sim.wheels.t_ns.tolist()):
            wl, wr = float(sim.wheels.omega_l[i]), float(sim.wheels.omega_r[i])
            pos = None if wrapped[i] is None else [wrapped[i][0]] * 2 + [wrapped[i][1]] * 2
            writer.write_joint_state('/joint_states', t_ns, JOINT_NAMES, [wl, wl, wr, wr],
                                     positions=pos)
    return wrapped


@pytest.mark.parametrize('signal, hostile', [('position', False), ('auto', True),
                                             ('position', True)])
def test_node_and_predict_read_encoder_positions_alike(tmp_path, signal, hostile):
    sim = simulate(SimConfig(duration_s=8.0, seed=7, encoder_noise_rad_s=0.3))
    assert np.ptp(sim.wheel_pos_l) > 2 * math.pi  # the simulator writes turning joint angles
    positions = _encoder_bag(tmp_path / 'bag', sim, hostile)
    flat = {'robot': 'sim', 'wheel_radius': sim.config.geometry.wheel_radius,
            'track_width': sim.config.geometry.track_width, 'model': 'ideal_dd',
            'interval': 'ending', 'wheel_signal': signal, 'max_wheel_speed': 30.0}
    path = write_params_file(tmp_path / 'p.yaml', flat, {'source': 'test'})
    config = OdometryConfig.from_file(path)
    with open_recording(tmp_path / 'bag') as rec:  # what skidkin predict / calibrate read
        wheels = rec.read_wheels(max_wheel_speed_rad_s=30.0, wheel_signal=signal)
        notes = list(rec.notes)
    assert any(f'wheel_signal {signal}' in note for note in notes)
    expected = Odometer.from_config(config).predict(wheels, jumps_dropped=True)
    result = replay_through_node(sim.wheels, params_file=path, positions=positions)
    node = dict(zip(result.t_ns.tolist(), result.poses[:, :2].tolist()))
    offline = dict(zip(expected.t_ns.tolist(), expected.poses[:, :2].tolist()))
    assert set(node) == set(offline)  # the same samples rejected
    assert all(node[t] == offline[t] for t in node)  # bit for bit
    # skidkin predict reads the bag with the file's wheel_signal (9 decimals in its CSV)
    out = tmp_path / 'pred.csv'
    assert main(['predict', str(tmp_path / 'bag'), '--params', str(path), '--out',
                 str(out)]) == 0
    rows = out.read_text().splitlines()[1:]
    assert len(rows) == len(wheels)
    last = rows[-1].split(',')
    np.testing.assert_allclose([float(last[2]), float(last[3])], expected.poses[-1, :2],
                               atol=2e-9)
    # calibrate writes the signal it read, so the node reads the same; a table has speeds only
    loaded = load_source(tmp_path / 'bag', SourceOptions(wheel_signal=signal,
                                                         max_wheel_speed_rad_s=30.0),
                         need_truth=False)
    assert input_parameters([loaded])['wheel_signal'] == signal
    assert np.array_equal(loaded.drives[0].wheels.omega_l, wheels.omega_l)
    table = write_truth_csv(sim, tmp_path / 'drive.csv')
    notes = load_source(table, SourceOptions(wheel_signal=signal)).notes
    assert any('holds wheel speeds only' in note for note in notes)
    other = 'velocity' if signal != 'velocity' else 'auto'
    assert main(['predict', str(tmp_path / 'bag'), '--params', str(path), '--out',
                 str(tmp_path / 'no.csv'), '--wheel-signal', other]) == 2
    dropped = len(sim.wheels) - len(wheels)
    counters = result.counters
    if hostile:
        # NaN (position) and the counter step: counted like bad speeds; without positions:
        # refused by position, taken from the velocities by auto
        assert counters.get('non_finite', 0) == (1 if signal == 'position' else 0)
        assert counters.get('implausible', 0) == 1
        assert counters.get('no_position', 0) == (3 if signal == 'position' else 0)
        assert dropped == sum(counters.get(k, 0) for k in ('non_finite', 'implausible',
                                                           'no_position'))
    else:
        assert dropped == 0 and counters.get('implausible', 0) == 0
        # the speeds are the travel over each interval, not the noisy velocities (0.3 rad/s)
        true = sim.wheels_true.omega_l
        assert np.sqrt(np.mean((wheels.omega_l[1:] - true[1:]) ** 2)) < 0.1
        assert np.sqrt(np.mean((sim.wheels.omega_l[1:] - true[1:]) ** 2)) > 0.25


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
    assert_replay_matches(result, expected)   # twists bit for bit, poses to 1e-12
    # the rate terms matter: without them the forward speed differs
    plain = dict(RATE_DEPENDENT, **{'augmented.extensions': 'component_lags'})
    other = Odometer.from_config(OdometryConfig.from_file(write_params_file(
        tmp_path / 'plain.yaml', plain, {'source': 'test'}))).predict(wheels)
    assert np.abs(other.twists[:, 0] - expected.twists[:, 0]).max() > 0.01


def test_node_runs_the_backlash_bit_for_bit(tmp_path):
    """The play's state per wheel (C203): the node and predict take it alike, sample by sample."""
    wheels = simulate(SimConfig(duration_s=12.0, seed=6)).wheels
    values = {**{k: v for k, v in AUGMENTED.items()
                 if not k.startswith(('augmented.time_offset', 'augmented.terrain_regime'))},
              'augmented.extensions': 'backlash, lateral_skid, first_order_lag',
              'augmented.backlash.play_rad': 0.4}
    path = write_params_file(tmp_path / 'backlash.yaml', values, {'source': 'test'})
    expected = Odometer.from_config(OdometryConfig.from_file(path)).predict(wheels)
    result = replay_through_node(wheels, params_file=path)
    assert_replay_matches(result, expected)   # twists bit for bit, poses to 1e-12
    # the play matters on this drive: without it the path goes elsewhere
    plain = dict(values, **{'augmented.extensions': 'lateral_skid, first_order_lag'})
    del plain['augmented.backlash.play_rad']
    other = Odometer.from_config(OdometryConfig.from_file(write_params_file(
        tmp_path / 'plain.yaml', plain, {'source': 'test'}))).predict(wheels)
    assert np.abs(other.poses[-1] - expected.poses[-1]).max() > 1e-3


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
# ROC is not linear in the wheel speeds: its sensitivity is differentiated at each step's speeds.
# The per-second noise part is set too, so every part of the noise model goes through the node.
CALIBRATED_ROC = {
    'wheel_radius': 0.1651, 'track_width': 0.555, 'robot': 'sim_husky', 'model': 'roc',
    'models.roc.alpha': 0.9, 'models.roc.beta_1': 0.6, 'models.roc.beta_2': 0.3,
    'models.roc.noise.calibrated': True,
    'models.roc.noise.var_x_per_m': 4e-4, 'models.roc.noise.var_y_per_m': 1e-4,
    'models.roc.noise.var_yaw_per_m': 2e-5, 'models.roc.noise.var_yaw_per_rad': 5e-4,
    'models.roc.noise.var_x_per_s': 3e-4, 'models.roc.noise.var_yaw_per_s': 2e-4,
    'models.roc.parameter_covariance': [1e-4, 0.0, 0.0, 0.0, 4e-4, 0.0, 0.0, 0.0, 9e-4],
}


@pytest.mark.parametrize('use,calibrated',
                         [(True, CALIBRATED), (False, CALIBRATED), (True, CALIBRATED_ROC)])
def test_node_publishes_the_covariance_of_predict_bit_for_bit(tmp_path, use, calibrated):
    """Length-independent noise and parameter covariance: the node == Odometer.predict."""
    sim = simulate(SimConfig(duration_s=8.0, seed=7))
    wheels = sim.wheels
    flat = dict(calibrated, use_parameter_covariance=use)
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
