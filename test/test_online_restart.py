"""Grounds that survive a restart: saved by ~/save_calibration, known again at the next start."""

import math

import numpy as np
import pytest
from skidkin_ros.cli.main import main
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.core.odometry.config import OdometryConfig, read_params_file, write_params_file
from skidkin_ros.core.odometry.saved_grounds import GROUND_NAMES
from skidkin_ros.core.online import online_odometer
from skidkin_ros.core.online.save import learned_values, save_learned
from skidkin_ros.errors import ConfigError
from skidkin_ros.sim.effects import make_effect
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate

FILE = {'model': 'edd_asymmetric', 'robot': 'sim_husky',
        **{f'models.edd_asymmetric.{k}': v for k, v in DEFAULT_TRUE_PARAMS.items()},
        'models.edd_asymmetric.noise.calibrated': True, 'online.enabled': True}
ALTERNATING = (make_effect('terrain_regime', 0.25, mode='alternate', period_m=4.0, yaw=0.15),)


def _reference(sim, seed):
    rng = np.random.default_rng(seed)
    t = np.arange(sim.start_ns, sim.end_ns, 100_000_000)
    truth = sim.truth_at(t)
    return PoseTrack(t, truth.x + rng.normal(0, 0.01, t.size),
                     truth.y + rng.normal(0, 0.01, t.size),
                     truth.yaw + rng.normal(0, 0.003, t.size))


@pytest.fixture(scope='module')
def learned_drive():
    """Learn a drive alternating between two grounds online from the file (2 grounds)."""
    sim = simulate(SimConfig(duration_s=120.0, seed=3, effects=ALTERNATING))
    config = OdometryConfig.from_flat(FILE)
    odometer = online_odometer(config)
    odometer.predict(sim.wheels, reference=_reference(sim, 3))
    assert len(odometer.learner.grounds) == 2
    return config, odometer.learner


def test_saved_file_carries_every_ground_and_the_next_start_knows_them(tmp_path, learned_drive):
    config, learner = learned_drive
    path = save_learned(config, learner, tmp_path / 'saved.yaml')
    flat = read_params_file(path)
    other = next(g for g in learner.grounds if g is not learner.active)
    assert flat['online.grounds.model'] == 'edd_asymmetric'
    assert flat['online.grounds.parameter_names'] == 'alpha_l, alpha_r, x_v, y_l, y_r'
    assert flat['online.grounds.parameters'] == other.k.tolist()
    assert flat['online.grounds.learned_m'] == [other.learned_m] and other.learned_m > 1.0
    cov = np.asarray(flat['online.grounds.covariance']).reshape(5, 5)
    np.testing.assert_allclose(cov, np.linalg.inv(other.info)
                               * np.outer(learner.scale, learner.scale), rtol=1e-12)
    # the next start: the active ground from the model's parameters, the other one remembered
    restarted = online_odometer(OdometryConfig.from_file(path)).learner
    assert len(restarted.grounds) == 2 and restarted.active is restarted.grounds[0]
    assert np.array_equal(restarted.active.k, learner.active.k)
    assert np.array_equal(restarted.grounds[1].k, other.k)
    assert restarted.grounds[1].learned_m == other.learned_m
    np.testing.assert_allclose(restarted.grounds[1].anchor, other.k, rtol=0)
    assert restarted.counters['online_grounds_remembered'] == 1
    # saved again before anything is learned: the same grounds (memory survives restarts)
    again = learned_values(OdometryConfig.from_file(path), restarted)
    assert again['online.grounds.parameters'] == flat['online.grounds.parameters']
    np.testing.assert_allclose(again['online.grounds.covariance'],
                               flat['online.grounds.covariance'], rtol=1e-9)


def test_a_file_without_grounds_runs_as_before(tmp_path):
    """No online.grounds.*: one ground, nothing written, the same odometry to the bit."""
    sim = simulate(SimConfig(duration_s=30.0, seed=5, effects=ALTERNATING))
    plain = OdometryConfig.from_flat(FILE)
    empty = OdometryConfig.from_flat({**FILE, 'online.grounds.parameters': [],
                                      'online.grounds.covariance': None,
                                      'online.grounds.learned_m': [],
                                      'online.grounds.model': ''})
    runs = []
    for config in (plain, empty):
        odometer = online_odometer(config)
        assert len(odometer.learner.grounds) == 1
        runs.append(odometer.predict(sim.wheels, reference=_reference(sim, 5)))
        assert 'online_grounds_remembered' not in odometer.counters
    assert np.array_equal(runs[0].poses, runs[1].poses)
    assert np.array_equal(runs[0].pose_covariances, runs[1].pose_covariances)
    # a learner with one ground saves no online.grounds.* entry (an empty list is not written)
    odometer = online_odometer(plain)
    path = save_learned(plain, odometer.learner, tmp_path / 'one.yaml')
    assert 'parameter_names' not in path.read_text()
    assert not set(GROUND_NAMES) & set(read_params_file(path))


def _grounds(**changes):
    k = [0.7, 0.65, -0.05, 0.45, -0.5]
    cov = (np.eye(5) * 1e-4).ravel().tolist()
    flat = {**FILE, 'online.grounds.model': 'edd_asymmetric',
            'online.grounds.parameter_names': 'alpha_l, alpha_r, x_v, y_l, y_r',
            'online.grounds.parameters': k, 'online.grounds.covariance': cov,
            'online.grounds.learned_m': [12.0]}
    flat.update(changes)
    return flat


BAD_GROUNDS = {
    'wrong length': ({'online.grounds.parameters': [0.7, 0.65, -0.05, 0.45]},
                     'n x 5 (got 4)'),
    'covariance length': ({'online.grounds.covariance': [1e-4] * 24}, 'n x 25 (got 24)'),
    'non-finite': ({'online.grounds.parameters': [0.7, math.nan, -0.05, 0.45, -0.5]},
                   'non-finite'),
    'infinite covariance': ({'online.grounds.covariance': [math.inf] * 25}, 'non-finite'),
    'not positive definite': ({'online.grounds.covariance': [1e-4] * 25},
                              'not positive definite'),
    'not symmetric': ({'online.grounds.covariance':
                       (np.eye(5) * 1e-4 + np.triu(np.ones((5, 5)), 1) * 1e-5).ravel().tolist()},
                      'not symmetric'),
    'too many': ({'online.max_grounds': 1.0}, 'raise online.max_grounds to 2'),
    'other model': ({'online.grounds.model': 'full_linear'}, "set model back to 'full_linear'"),
    'other parameters': ({'online.grounds.parameter_names': 'alpha_l, alpha_r'},
                         'online calibration of this model learns'),
    'out of range': ({'online.grounds.parameters': [1.7, 0.65, -0.05, 0.45, -0.5]},
                     "'models.edd_asymmetric.alpha_l'"),
    'negative metres': ({'online.grounds.learned_m': [-1.0]}, 'is negative'),
    'not numbers': ({'online.grounds.parameters': ['a', 'b']}, 'must be a list of numbers'),
}


@pytest.mark.parametrize('case', sorted(BAD_GROUNDS))
def test_grounds_that_do_not_fit_the_model_are_refused_with_what_to_do(case):
    changes, expected = BAD_GROUNDS[case]
    with pytest.raises(ConfigError) as err:
        OdometryConfig.from_flat(_grounds(**changes))
    assert expected in str(err.value)
    assert 'online.grounds' in str(err.value) or 'online.max_grounds' in str(err.value)
    OdometryConfig.from_flat(_grounds())   # the same file with sound grounds loads


@pytest.mark.parametrize('name', ['online.grounds.covariance',
                                  'models.edd_asymmetric.parameter_covariance'])
def test_a_covariance_too_small_to_invert_is_refused_c288(name):
    """1e-310 (a hand edit, a denormal): its information was inf, the learner's values NaN."""
    tiny = (np.eye(5) * 1e-310).ravel().tolist()
    with pytest.raises(ConfigError) as err:
        OdometryConfig.from_flat(_grounds(**{name: tiny}))
    assert name in str(err.value)
    assert 'write 0 where an entry is meant to be zero' in str(err.value)
    # 1e-30 still loads, and the learner's information stays finite
    config = OdometryConfig.from_flat(_grounds(**{name: (np.eye(5) * 1e-30).ravel().tolist()}))
    learner = online_odometer(config).learner
    assert len(learner.grounds) == 2
    assert all(np.isfinite(g.info).all() for g in learner.grounds)


def test_predict_refuses_unfit_grounds_without_a_traceback(tmp_path, capsys):
    path = tmp_path / 'bad.yaml'
    text = write_params_file(tmp_path / 'good.yaml', _grounds(), {'source': 'test'}).read_text()
    path.write_text(text.replace('learned_m: [12.0]', 'learned_m: [12.0, 3.0]'))
    table = tmp_path / 'table.csv'
    table.write_text('t,omega_l,omega_r\n0,1,1\n0.05,1,1\n')
    code = main(['predict', str(table), '--params', str(path), '--out', str(tmp_path / 'o.csv')])
    err = capsys.readouterr().err
    assert code != 0 and 'Traceback' not in err
    assert 'online.grounds.learned_m with n values (got 2)' in err


@pytest.mark.ros
def test_node_and_predict_agree_with_a_file_carrying_grounds(tmp_path, learned_drive):
    from skidkin_ros.core.rotation import quaternion_to_yaw, yaw_to_quaternion
    from node_harness import assert_online_replay_matches
    from skidkin_ros.node.replay import replay_through_node

    config, learner = learned_drive
    path = save_learned(config, learner, tmp_path / 'saved.yaml')
    assert 'online.grounds.parameters' in read_params_file(path)
    sim = simulate(SimConfig(duration_s=40.0, seed=4, effects=ALTERNATING))
    reference = sim.truth_at(np.arange(sim.start_ns, sim.end_ns, 100_000_000))
    wire_yaw = [quaternion_to_yaw(*yaw_to_quaternion(float(v))) for v in reference.yaw]
    odometer = online_odometer(OdometryConfig.from_file(path))
    expected = odometer.predict(sim.wheels, reference=PoseTrack(
        reference.t_ns, reference.x, reference.y, np.array(wire_yaw)))
    # the remembered ground was taken back on this drive (no new ground learned)
    assert odometer.counters['online_switch'] >= 1
    assert odometer.counters['online_grounds_remembered'] == 1
    result = replay_through_node(sim.wheels, params_file=path, reference=reference,
                                 timeout_s=120.0)
    assert_online_replay_matches(result, expected, sim.wheels)
    for cause in ('online_segments', 'online_change', 'online_switch',
                  'online_grounds_remembered'):
        assert result.counters.get(cause, 0) == odometer.counters[cause], cause


@pytest.mark.ros
def test_node_refuses_unfit_grounds_at_start_with_what_to_do():
    from node_harness import NodeRig

    bad = _grounds(**{'online.grounds.covariance': [1e-4] * 25})
    with pytest.raises(ConfigError) as err:
        NodeRig(bad)
    assert 'not positive definite' in str(err.value) and 'online.grounds' in str(err.value)
    rig = NodeRig(_grounds())   # sound grounds: the node starts knowing them
    try:
        assert len(rig.node._odometer.learner.grounds) == 2
    finally:
        rig.close()


def test_a_remembered_ground_todays_drive_refutes_is_forgotten():
    """Drop yesterday's second ground where today's second ground is another.

    It goes at the change that starts the new ground, so it cannot win the recognition there.
    """
    base = DEFAULT_TRUE_PARAMS
    second = {'alpha_l': base['alpha_l'] * 0.75, 'alpha_r': base['alpha_r'] * 0.75,
              'x_v': base['x_v'] / 0.85, 'y_l': base['y_l'] * 0.75 / 0.85,
              'y_r': base['y_r'] * 0.75 / 0.85}
    flat = _grounds(**{'online.grounds.parameters': list(second.values()),
                       'online.grounds.covariance': (np.eye(5) * 1e-5).ravel().tolist()})
    third = (make_effect('terrain_regime', 0.4, mode='alternate', period_m=4.0, yaw=0.02),)
    sim = simulate(SimConfig(duration_s=60.0, seed=7, effects=third))
    odometer = online_odometer(OdometryConfig.from_flat(flat))
    remembered = odometer.learner.grounds[1]
    odometer.predict(sim.wheels, reference=_reference(sim, 7))
    assert odometer.counters['online_change'] >= 1
    assert odometer.counters['online_grounds_forgotten'] == 1
    assert remembered not in odometer.learner.grounds
    # the same file on a drive over its own two grounds: taken back and learned, never dropped
    same = simulate(SimConfig(duration_s=60.0, seed=7, effects=ALTERNATING))
    odometer = online_odometer(OdometryConfig.from_flat(flat))
    remembered = odometer.learner.grounds[1]
    odometer.predict(same.wheels, reference=_reference(same, 7))
    assert odometer.counters['online_switch'] >= 1 and remembered.segments >= 1
    assert 'online_grounds_forgotten' not in odometer.counters


def test_an_augmented_models_grounds_round_trip():
    from skidkin_ros.core.online.grounds import Ground

    flat = {**FILE, 'model': 'augmented', 'augmented.base': 'edd_asymmetric',
            'augmented.extensions': 'lateral_skid, speed_slip'}
    config = OdometryConfig.from_flat(flat)
    learner = online_odometer(config).learner
    other = Ground(1, learner.active.k * 0.95, 2.0 * learner.active.info)
    learner.grounds.append(other)
    values = learned_values(config, learner)
    assert values['online.grounds.parameter_names'] == ('alpha_l, alpha_r, x_v, y_l, y_r, '
                                                        'speed_slip.k, lateral_skid.k')
    restarted = online_odometer(OdometryConfig.from_flat(values)).learner
    assert len(restarted.grounds) == 2 and np.array_equal(restarted.grounds[1].k, other.k)
    # the same grounds under other extensions: refused, naming what the learner learns
    with pytest.raises(ConfigError, match='online calibration of this model learns'):
        OdometryConfig.from_flat({**values, 'augmented.extensions': 'lateral_skid'})


def test_save_and_restart_cycles_keep_the_active_grounds_uncertainty_c290():
    """A week of daily restarts with nothing learned: the saved covariance does not shrink.

    The broad prior (online.prior_sigma) was added to the file's covariance at every start,
    and the save wrote that back: sigma 0.5 -> 0.18 of a typical magnitude in 7 cycles.
    """
    config = OdometryConfig.from_flat(FILE)
    first = online_odometer(config).learner.covariance
    for _ in range(7):
        config = OdometryConfig.from_flat(learned_values(config, online_odometer(config).learner))
    np.testing.assert_allclose(online_odometer(config).learner.covariance, first, rtol=1e-9)
    # an offline fit's covariance narrower than the prior is taken as it is; broader
    # directions are held at the prior's width
    scale = online_odometer(config).learner.scale
    sigma = np.array([0.01, 0.02, 0.9, 0.01, 0.03]) * scale
    diagonal = np.diag(sigma ** 2).ravel().tolist()
    fitted = OdometryConfig.from_flat(
        {**FILE, 'models.edd_asymmetric.parameter_covariance': diagonal})
    got = np.sqrt(np.diag(online_odometer(fitted).learner.covariance)) / scale
    np.testing.assert_allclose(got, [0.01, 0.02, 0.5, 0.01, 0.03], rtol=1e-9)


@pytest.mark.ros
def test_remembered_grounds_set_at_runtime_through_the_parameter_service():
    """`ros2 param set` of online.grounds.* (a real client): unfit values refused with what to do.

    One list at a time cannot stay consistent with the others: refused; the five entries set
    together (atomically) take effect. The odometry never stops and stays finite.
    """
    import math
    from node_harness import NodeRig
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    rig = NodeRig({**_grounds(), 'online.max_grounds': 3})
    try:
        client = AsyncParameterClient(rig.driver, rig.node.get_fully_qualified_name())
        rig.spin_until(client.services_are_ready, timeout_s=10.0, what='parameter services')

        def set_(params, atomic=False):
            future = (client.set_parameters_atomically if atomic
                      else client.set_parameters)(params)
            rig.spin_until(future.done, timeout_s=10.0, what='parameters set')
            result = future.result()
            return [result.result] if atomic else list(result.results)

        t_ns = [1_000_000_000]

        def drive():
            for _ in range(10):
                t_ns[0] += 20_000_000
                rig.send_joint(t_ns[0], 5.0, 4.0)
            rig.drain()
            position = rig.odom[-1].pose.pose.position
            assert math.isfinite(position.x) and math.isfinite(position.y)
            return len(rig.node._odometer.learner.grounds)

        assert drive() == 2
        refused = {'online.max_grounds': (1, 'raise online.max_grounds to 2'),
                   'online.grounds.parameters': ([0.7, 0.6], 'n x 5 (got 2)'),
                   'model': ('edd_symmetric', "set model back to 'edd_asymmetric'"),
                   'online.grounds.learned_m': ([1e308], 'beyond')}
        for name, (value, expected) in refused.items():
            (result,) = set_([Parameter(name, value=value)])
            assert not result.successful and expected in result.reason, (name, result.reason)
            assert drive() == 2
        (result,) = set_([Parameter('online.grounds.learned_m', value=[5])])   # an integer
        assert result.successful and drive() == 2
        empty = [Parameter('online.grounds.model', value=''),
                 Parameter('online.grounds.parameter_names', value='')] + [
            Parameter(name, Parameter.Type.DOUBLE_ARRAY, []) for name in
            ('online.grounds.parameters', 'online.grounds.covariance', 'online.grounds.learned_m')]
        (result,) = set_(empty, atomic=True)
        assert result.successful and drive() == 1
    finally:
        rig.close()
