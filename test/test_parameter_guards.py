"""Parameters that cannot be honoured, and joints changed at runtime under encoder positions.

A model the file does not hold, covariances and values that overflow, integers beyond 64
bits: the same rules hold in the node (at start-up and at runtime) and in the offline commands.
"""

import math

import pytest
from skidkin_ros.adapters.sim_writer import write_truth_csv
from skidkin_ros.cli.main import main
from skidkin_ros.core.odometry.config import (check_model_given, OdometryConfig,
                                              write_params_file)
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.errors import ParameterError
from skidkin_ros.sim.simulate import SimConfig, simulate

EDD = {'model': 'edd_symmetric', 'models.edd_symmetric.noise.calibrated': True,
       'models.edd_symmetric.alpha': 0.9, 'models.edd_symmetric.b_hat': 0.7}
NS = 1_000_000_000


@pytest.fixture(scope='module')
def table(tmp_path_factory):
    folder = tmp_path_factory.mktemp('drive')
    return write_truth_csv(simulate(SimConfig(duration_s=6.0, seed=3)), folder / 'drive.csv')


def _published(config, n=60):
    odometer = Odometer.from_config(config)
    count = 0
    for k in range(n):
        t_ns = 1000 * NS + k * 20_000_000
        count += odometer.joint_sample(t_ns, 3.0, 4.0, t_ns) is not None
    return count


# ---------------------------------------------------------------- overflowing values
@pytest.mark.parametrize('name, value', [
    ('models.edd_symmetric.parameter_covariance', [1e308, 0.0, 0.0, 1e308]),
    ('models.edd_symmetric.parameter_covariance', [1e150, 0.0, 0.0, 1e150]),
    ('models.edd_symmetric.noise.var_x_per_m', 1e308),
    ('models.edd_symmetric.noise.var_yaw_per_s', 1e200),
    ('pose_covariance_diagonal', [1e308] * 6),
    ('twist_covariance_diagonal', [1.0] * 5 + [1e300]),
    ('models.edd_symmetric.b_hat', 1e300),
    ('models.full_linear.gamma_11', -1e200),
])
def test_values_that_would_overflow_the_covariance_are_refused(name, value):
    with pytest.raises(ParameterError, match=f"'{name}' holds .*beyond") as err:
        OdometryConfig.from_flat({**EDD, name: value})
    assert 'never publish' in str(err.value)


def test_the_largest_accepted_values_still_publish_every_sample():
    flat = {**EDD, 'models.edd_symmetric.parameter_covariance': [1e12, 0.0, 0.0, 1e12],
            'models.edd_symmetric.noise.var_x_per_m': 1e12, 'models.edd_symmetric.b_hat': 1e9}
    assert _published(OdometryConfig.from_flat(flat)) == 60
    fallback = {'pose_covariance_diagonal': [1e12] * 6, 'twist_covariance_diagonal': [1e12] * 6}
    assert _published(OdometryConfig.from_flat(fallback)) == 60


@pytest.mark.parametrize('name, value', [
    ('max_rate', 10 ** 400), ('wheel_radius', -10 ** 400), ('schema_version', 10 ** 19),
    ('models.edd_symmetric.parameter_covariance', [10 ** 400, 0, 0, 1]),
    ('pose_covariance_diagonal', [1, 1, 1, 1, 1, 10 ** 400]), ('imu.scale', 10 ** 400),
])
def test_integers_beyond_64_bits_are_refused_not_an_overflow_traceback(name, value):
    with pytest.raises(ParameterError, match='64-bit integers a ROS parameter holds'):
        OdometryConfig.from_flat({**EDD, name: value})


def test_predict_and_evaluate_refuse_a_400_digit_integer_with_exit_2(table, tmp_path, capsys):
    params = tmp_path / 'p.yaml'
    write_params_file(params, EDD)
    params.write_text(params.read_text().replace('b_hat: 0.7', 'b_hat: ' + '7' * 400))
    for argv in (['predict', str(table), '--params', str(params), '--out',
                  str(tmp_path / 'o.csv')],
                 ['evaluate', str(table), '--params', str(params)]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert '400 digits' in err and 'Traceback' not in err
    assert not (tmp_path / 'o.csv').exists()


# ---------------------------------------------------------------- a model the file lacks
def test_predict_refuses_a_model_the_file_does_not_hold(table, tmp_path, capsys):
    params = tmp_path / 'p.yaml'
    write_params_file(params, EDD)
    out = tmp_path / 'o.csv'
    assert main(['predict', str(table), '--params', str(params), '--model', 'roc',
                 '--out', str(out)]) == 2
    err = capsys.readouterr().err
    assert "model 'roc' is not in the file" in err and 'edd_symmetric' in err
    assert not out.exists()
    # the file's model, ideal_dd (no parameters) and a model it holds are fine
    for model in ('edd_symmetric', 'ideal_dd'):
        assert main(['predict', str(table), '--params', str(params), '--model', model,
                     '--out', str(out), '--force']) == 0
    with pytest.raises(ParameterError, match='holds ideal_dd, edd_symmetric'):
        check_model_given('roc', ('ideal_dd', 'edd_symmetric'), 'the file')


def _joint_state(t_ns, names, velocity, position):
    from sensor_msgs.msg import JointState
    from skidkin_ros.node.conversions import ns_to_stamp
    msg = JointState()
    msg.header.stamp = ns_to_stamp(t_ns)
    msg.name = list(names)
    msg.velocity = [float(v) for v in velocity]
    msg.position = [float(p) for p in position]
    return msg


def test_node_refuses_a_runtime_model_whose_parameters_it_was_not_given(make_rig, tmp_path):
    from rclpy.parameter import Parameter
    params = write_params_file(tmp_path / 'p.yaml', EDD)
    rig = make_rig(params_file=params)
    node = rig.node
    result = node.set_parameters([Parameter('model', value='roc')])[0]
    assert not result.successful
    assert "model 'roc' is not in" in result.reason and 'models.roc.* parameters first' in (
        result.reason)
    assert node.config.model == 'edd_symmetric'
    results = node.set_parameters([Parameter('model', value='ideal_dd'),
                                   Parameter('model', value='edd_symmetric')])
    assert all(r.successful for r in results)
    results = node.set_parameters([Parameter('models.roc.alpha', value=0.8),
                                   Parameter('model', value='roc')])
    assert all(r.successful for r in results), [r.reason for r in results]
    assert node.config.model == 'roc'
    # an overflowing covariance at runtime is refused (it answered successful and went silent)
    result = node.set_parameters([Parameter('models.roc.parameter_covariance',
                                            value=[1e308] + [0.0] * 15)])[0]
    assert not result.successful and 'beyond 1e+12' in result.reason


def test_node_does_not_difference_the_old_joint_against_the_new_one(make_rig):
    # Standing still: the left joints read 0.00 and 0.05 rad (an encoder offset). Choosing the
    # other left joint at runtime is no travel (it read a 0.015 rad turn).
    from rclpy.parameter import Parameter
    from node_harness import wall_ns
    names = ['left_a', 'left_b', 'right_a']
    rig = make_rig({'wheel_signal': 'position', 'left_wheel_joints': ['left_a'],
                    'right_wheel_joints': ['right_a']})
    t0 = wall_ns() - 5 * NS
    for k in range(3):
        rig.send(_joint_state(t0 + k * 20_000_000, names, [0.0] * 3, [0.0, 0.05, 0.0]))
    result = rig.node.set_parameters([Parameter('left_wheel_joints', value=['left_b'])])[0]
    assert result.successful
    for k in range(3, 6):
        rig.send(_joint_state(t0 + k * 20_000_000, names, [0.0] * 3, [0.0, 0.05, 0.0]))
    x, y, yaw = rig.node.pose
    assert (x, y, yaw) == (0.0, 0.0, 0.0)
    assert rig.node.counters['implausible'] == 0 and math.isfinite(yaw)
