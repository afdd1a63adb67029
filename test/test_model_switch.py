"""Switching to `augmented` needs an augmented model: without one it would be an ideal drive."""

import re

from skidkin_ros.adapters.sim_writer import write_truth_csv
from skidkin_ros.cli.main import main
from skidkin_ros.core.odometry.config import models_held, write_params_file
from skidkin_ros.sim.simulate import SimConfig, simulate

# What `skidkin calibrate` writes, reduced: a calibrated base model and no augmented.*.
CALIBRATED = {'model': 'edd_symmetric', 'models.edd_symmetric.noise.calibrated': True,
              'models.edd_symmetric.alpha': 0.9, 'models.edd_symmetric.b_hat': 0.7}
# What `skidkin diagnose` adds.
DIAGNOSED = {'augmented.base': 'edd_symmetric', 'augmented.extensions': 'time_offset',
             'augmented.time_offset.offset_s': 0.05}


def test_augmented_is_held_only_when_its_base_is_given():
    assert 'augmented' not in models_held(f'models.edd_symmetric.{p}' for p in ('alpha',))
    assert 'augmented' in models_held(DIAGNOSED)
    assert 'augmented' in models_held(['augmented.base'])
    # extensions alone run them on the default base, ideal_dd: not a calibration
    assert 'augmented' not in models_held(['augmented.extensions', 'models.roc.alpha'])


def test_n145_predict_refuses_augmented_from_a_file_without_one(tmp_path, capsys):
    table = write_truth_csv(simulate(SimConfig(duration_s=6.0, seed=3)), tmp_path / 'd.csv')
    plain = write_params_file(tmp_path / 'calibrated.yaml', CALIBRATED)
    out = tmp_path / 'o.csv'
    assert main(['predict', str(table), '--params', str(plain), '--model', 'augmented',
                 '--out', str(out)]) == 2
    err = capsys.readouterr().err
    assert "model 'augmented' is not in the file" in err and 'ideal_dd (its default base)' in err
    assert 'skidkin diagnose' in err and 'Traceback' not in err and not out.exists()
    diagnosed = write_params_file(tmp_path / 'augmented.yaml', {**CALIBRATED, **DIAGNOSED})
    assert main(['predict', str(table), '--params', str(diagnosed), '--model', 'augmented',
                 '--out', str(out)]) == 0


def test_n145_the_node_warns_at_start_and_refuses_at_runtime_an_augmented_it_lacks(
        make_rig, tmp_path, capfd):
    from rclpy.parameter import Parameter
    rig = make_rig(params_file=write_params_file(tmp_path / 'p.yaml', CALIBRATED))
    result = rig.node.set_parameters([Parameter('model', value='augmented')])[0]
    assert not result.successful
    assert "model 'augmented' is not in" in result.reason
    assert '(set its augmented.base parameters first)' in result.reason
    assert rig.node.config.model == 'edd_symmetric'
    results = rig.node.set_parameters([Parameter(name, value=value)
                                       for name, value in DIAGNOSED.items()]
                                      + [Parameter('model', value='augmented')])
    assert all(r.successful for r in results), [r.reason for r in results]
    assert rig.node.config.model == 'augmented'
    capfd.readouterr()
    make_rig(overrides={'model': 'augmented'},
             params_file=write_params_file(tmp_path / 'q.yaml', CALIBRATED))
    err = capfd.readouterr().err
    assert "model 'augmented' runs default parameters (an ideal drive)" in err
    assert 'no augmented.base parameter was given' in err


def test_n146_the_node_says_which_topics_its_gyro_and_online_calibration_read(
        make_rig, tmp_path, capfd):
    from rclpy.parameter import Parameter
    params = write_params_file(tmp_path / 'p.yaml', CALIBRATED)
    capfd.readouterr()
    rig = make_rig(overrides={'online.enabled': True, 'imu.mode': 'fuse'}, params_file=params)
    err = capfd.readouterr().err
    # the resolved names: the rig runs in a namespace of its own
    assert re.search(r'imu.mode fuse: the gyro is read from sensor_msgs/Imu on /\S*imu/data', err)
    assert re.search(r'online calibration on: learning from nav_msgs/Odometry on '
                     r'/\S*reference/odom', err)
    results = rig.node.set_parameters([Parameter('online.enabled', value=False),
                                       Parameter('imu.mode', value='off')])
    assert all(r.successful for r in results), [r.reason for r in results]
    err = capfd.readouterr().err
    assert 'online calibration off' in err and 'imu.mode off' in err
    make_rig(params_file=params)
    err = capfd.readouterr().err
    assert 'online calibration' not in err and 'imu.mode' not in err


def test_n147_augmented_extensions_without_a_base_are_not_a_calibration(make_rig, tmp_path,
                                                                        capfd):
    """Extensions alone would run on ideal_dd (the default base): warned, refused, refused."""
    from rclpy.parameter import Parameter
    plain = write_params_file(tmp_path / 'calibrated.yaml', CALIBRATED)
    capfd.readouterr()
    make_rig(overrides={'model': 'augmented', 'augmented.extensions': 'time_offset'},
             params_file=plain)
    assert 'no augmented.base parameter was given' in capfd.readouterr().err
    rig = make_rig(params_file=plain)
    results = rig.node.set_parameters([Parameter('augmented.extensions', value='time_offset'),
                                       Parameter('model', value='augmented')])
    assert results[0].successful and not results[1].successful
    assert '(set its augmented.base parameters first)' in results[1].reason
    assert rig.node.config.model == 'edd_symmetric'
    # the base named: the calibrated model with the extension
    result = rig.node.set_parameters([Parameter('augmented.base', value='edd_symmetric')])[0]
    assert result.successful
    assert rig.node.set_parameters([Parameter('model', value='augmented')])[0].successful
    assert rig.node.config.augmented_base == 'edd_symmetric'
    assert rig.node.config.augmented_extensions == ('time_offset',)
    table = write_truth_csv(simulate(SimConfig(duration_s=6.0, seed=3)), tmp_path / 'd.csv')
    half = write_params_file(tmp_path / 'half.yaml',
                             {**CALIBRATED, 'augmented.extensions': 'time_offset'})
    capfd.readouterr()
    assert main(['predict', str(table), '--params', str(half), '--model', 'augmented',
                 '--out', str(tmp_path / 'o.csv')]) == 2
    err = capfd.readouterr().err
    assert 'no augmented.base was given' in err and 'Traceback' not in err
    assert not (tmp_path / 'o.csv').exists()


def test_n148_an_augmented_base_the_node_was_not_given_is_refused_at_runtime(make_rig, tmp_path):
    """augmented.base switched to a model without parameters would run its defaults."""
    from rclpy.parameter import Parameter
    diagnosed = {**CALIBRATED, **DIAGNOSED, 'model': 'augmented'}
    rig = make_rig(params_file=write_params_file(tmp_path / 'a.yaml', diagnosed))
    result = rig.node.set_parameters([Parameter('augmented.base', value='roc')])[0]
    assert not result.successful
    assert "runs the base model 'roc', which is not in" in result.reason
    assert '(set its models.roc.* parameters first)' in result.reason
    assert rig.node.config.augmented_base == 'edd_symmetric'
    # with roc's parameters given first, the switch is taken
    results = rig.node.set_parameters([Parameter('models.roc.alpha', value=0.9),
                                       Parameter('augmented.base', value='roc')])
    assert all(r.successful for r in results), [r.reason for r in results]
    assert rig.node.config.augmented_base == 'roc'
    # predict refuses the same file with a base it does not hold
    table = write_truth_csv(simulate(SimConfig(duration_s=6.0, seed=3)), tmp_path / 'd.csv')
    other = write_params_file(tmp_path / 'b.yaml', {**diagnosed, 'augmented.base': 'roc'})
    assert main(['predict', str(table), '--params', str(other), '--model', 'augmented',
                 '--out', str(tmp_path / 'o.csv')]) == 2
    assert not (tmp_path / 'o.csv').exists()


def test_c224_predict_warns_as_the_node_does_of_a_model_the_file_does_not_hold(
        make_rig, tmp_path, capfd):
    """A file whose own model has no parameters: the node warns, predict says the same line."""
    table = write_truth_csv(simulate(SimConfig(duration_s=6.0, seed=3)), tmp_path / 'd.csv')
    for name, flat in (('roc', {**CALIBRATED, 'model': 'roc'}),
                       ('aug', {**CALIBRATED, 'model': 'augmented',
                                'augmented.extensions': 'time_offset'})):
        params = write_params_file(tmp_path / f'{name}.yaml', flat)
        capfd.readouterr()
        make_rig(params_file=params)
        node_line = re.search(r'model .* load a calibrated file', capfd.readouterr().err)
        assert node_line is not None
        assert main(['predict', str(table), '--params', str(params),
                     '--out', str(tmp_path / f'{name}.csv')]) == 0
        out = capfd.readouterr().out
        assert f'warning: {params}: {node_line.group(0)}' in out
    # a file that holds its model: no warning from either
    params = write_params_file(tmp_path / 'ok.yaml', CALIBRATED)
    make_rig(params_file=params)
    assert main(['predict', str(table), '--params', str(params),
                 '--out', str(tmp_path / 'ok.csv')]) == 0
    captured = capfd.readouterr()
    assert 'default parameters' not in captured.out + captured.err
