"""The parameter schema, validation, and the ROS 2 parameters file round trip."""

import numpy as np
import pytest
from skidkin_ros.core.kinematics.models import MODELS
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.config import (OdometryConfig, parameter_schema, read_params_file,
                                              SCHEMA_VERSION, write_params_file)
from skidkin_ros.errors import ConfigError, OutputError, ParameterError
import yaml


def test_schema_declares_every_model_parameter_once_with_unit_and_range():
    schema = parameter_schema()
    names = [entry.name for entry in schema]
    assert len(names) == len(set(names))
    for model in MODELS.values():
        for spec in model.params:
            entry = next(e for e in schema if e.name == f'models.{model.name}.{spec.name}')
            assert spec.unit in entry.description and spec.range_text() in entry.description


def test_model_defaults_follow_the_geometry():
    schema = {e.name: e for e in parameter_schema(Geometry(0.2, 0.8))}
    assert schema['models.edd_symmetric.b_hat'].default == pytest.approx(0.8)
    assert schema['models.full_linear.gamma_32'].default == pytest.approx(0.25)


def test_empty_configuration_is_the_ideal_husky():
    config = OdometryConfig.from_flat({})
    assert config.model == 'ideal_dd' and config.active_noise is None
    assert config.geometry == Geometry(0.1651, 0.555)


@pytest.mark.parametrize('flat,needle', [
    ({'wheel_radius': 0.0}, 'wheel_radius'),
    ({'wheel_radius': float('nan')}, 'wheel_radius'),
    ({'track_width': 'wide'}, 'track_width'),
    ({'models.edd_symmetric.alpha': 2.0}, 'models.edd_symmetric.alpha'),
    ({'model': 'tank'}, 'model'),
    ({'input': 'can_bus'}, 'input'),
    ({'max_dt': -1.0}, 'max_dt'),
    ({'left_wheel_joints': []}, 'left_wheel_joints'),
    ({'twist_covariance_diagonal': [0.0] * 6}, 'twist_covariance_diagonal'),
    ({'publish_tf': 'yes'}, 'publish_tf'),
    ({'made_up': 1.0}, 'made_up'),
])
def test_invalid_values_name_the_parameter(flat, needle):
    with pytest.raises(ParameterError) as err:
        OdometryConfig.from_flat(flat)
    assert needle in str(err.value)


def test_schema_version_and_robot_mismatch_are_refused():
    with pytest.raises(ConfigError, match='schema_version'):
        OdometryConfig.from_flat({'schema_version': SCHEMA_VERSION + 1})
    with pytest.raises(ConfigError, match="'warthog'.*'husky'"):
        OdometryConfig.from_flat({'robot': 'warthog', 'expected_robot': 'husky'})


def test_params_file_round_trip_is_a_ros2_parameters_file(tmp_path):
    values = {'model': 'roc', 'robot': 'husky', 'wheel_radius': 0.17, 'track_width': 0.6,
              'models.roc.alpha': 0.9, 'models.roc.beta_1': 1, 'models.roc.beta_2': 0.5,
              'models.roc.noise.calibrated': True, 'models.roc.noise.var_x_per_m': 1e-4,
              'models.roc.noise.var_y_per_m': 2e-4, 'models.roc.noise.var_yaw_per_m': 3e-4,
              'models.roc.noise.var_yaw_per_rad': 4e-4}
    path = write_params_file(tmp_path / 'p.yaml', values, {'source': 'unit test'})
    document = yaml.safe_load(path.read_text())
    body = document['/**']['ros__parameters']
    assert body['models']['roc']['beta_1'] == 1.0 and isinstance(body['models']['roc']['beta_1'],
                                                                 float)
    assert body['provenance']['source'] == 'unit test'
    config = OdometryConfig.from_flat(read_params_file(path))
    assert config.model == 'roc' and config.geometry.track_width == 0.6
    assert config.active_noise.var_yaw_per_rad == 4e-4
    bound = config.bound_model()
    np.testing.assert_allclose(bound.k, [0.9, 1.0, 0.5])


def test_existing_file_is_not_overwritten_without_force(tmp_path):
    path = tmp_path / 'p.yaml'
    path.write_text('keep me')
    with pytest.raises(OutputError, match='--force'):
        write_params_file(path, {'model': 'ideal_dd'})
    assert path.read_text() == 'keep me'
    write_params_file(path, {'model': 'ideal_dd'}, force=True)
    assert 'ros__parameters' in path.read_text()


def test_invalid_values_are_never_written(tmp_path):
    with pytest.raises(ParameterError):
        write_params_file(tmp_path / 'p.yaml', {'models.roc.alpha': 3.0})
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize('text,needle', [
    ('', 'empty'), ('[1, 2]', 'mapping'), ('/**: {foo: 1}', 'ros__parameters'),
    (': : :', 'YAML')])
def test_unreadable_params_files_name_the_path(tmp_path, text, needle):
    path = tmp_path / 'bad.yaml'
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        read_params_file(path)
    assert str(path) in str(err.value) and needle in str(err.value)
    with pytest.raises(ConfigError, match='does not exist'):
        read_params_file(tmp_path / 'missing.yaml')


@pytest.mark.parametrize('flat,needle', [
    ({'max_rate': 1e-300}, 'max_rate'), ({'max_rate': 0.05}, 'at least 0.1 Hz'),
    ({'odom_frame_id': ''}, 'odom_frame_id'), ({'base_frame_id': ' base_link'}, 'base_frame_id'),
    ({'odom_frame_id': '/odom'}, 'starts with "/"'),
    ({'odom_frame_id': 'base_link'}, 'two different frames'),
    ({'max_stamp_step_back': 0.0}, 'max_stamp_step_back'),
    ({'max_wheel_acceleration': -1.0}, 'max_wheel_acceleration')])
def test_a_silent_publish_rate_and_unusable_frame_ids_are_refused(flat, needle):
    """N32: max_rate 1e-300 silenced /odom, an empty frame id was taken."""
    with pytest.raises(ParameterError) as err:
        OdometryConfig.from_flat(flat)
    assert needle in str(err.value)
    assert OdometryConfig.from_flat({'max_rate': 0.1})['max_rate'] == 0.1


def test_empty_params_file_refused_and_a_duplicate_key_warned(tmp_path, caplog):
    """C21: the node took an empty file, and a duplicate key won silently."""
    for text in ('', '# only a comment\n', '---\n'):
        empty = tmp_path / 'empty.yaml'
        empty.write_text(text)
        with pytest.raises(ConfigError, match='empty'):
            OdometryConfig.from_file(empty)
    dup = tmp_path / 'dup.yaml'
    dup.write_text('/**:\n  ros__parameters:\n    max_dt: 0.3\n    max_dt: 0.4\n')
    config = OdometryConfig.from_file(dup)
    assert config['max_dt'] == 0.4  # the last value, as rcl takes it
    assert "'max_dt' is given twice (line 4); the last value wins" in caplog.text


def _alias_bomb(depth):
    lines = ['a0: &a0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]']
    for i in range(1, depth):
        lines.append(f'a{i}: &a{i} [' + ', '.join([f'*a{i - 1}'] * 9) + ']')
    lines.append(f'/**:\n  ros__parameters:\n    max_dt: *a{depth - 1}\n')
    return '\n'.join(lines)


def test_alias_bomb_refused_at_once_and_echoed_values_are_short(tmp_path):
    """C22: 726 bytes of aliases ended in a MemoryError after 42 s."""
    bomb = tmp_path / 'bomb.yaml'
    bomb.write_text(_alias_bomb(9))
    assert len(bomb.read_bytes()) < 800
    with pytest.raises(ConfigError, match=r'alias \*a0 is not allowed'):
        read_params_file(bomb)
    merge = tmp_path / 'merge.yaml'
    merge.write_text('/**:\n  ros__parameters:\n    <<: {max_dt: 0.3}\n')
    with pytest.raises(ConfigError, match='merge keys'):
        read_params_file(merge)
    with pytest.raises(ParameterError) as err:
        OdometryConfig.from_flat({'max_dt': [[0.5] * 1000] * 1000})
    assert len(str(err.value)) < 400 and 'characters in all' in str(err.value)
    with pytest.raises(ParameterError) as err:
        OdometryConfig.from_flat({'left_wheel_joints': ['x' * 10**6, '']})
    assert len(str(err.value)) < 400


def test_params_file_that_is_not_a_regular_small_file_is_refused(tmp_path):
    """C31: /dev/zero as a file to read must not be read for ever."""
    with pytest.raises(ConfigError, match='not a regular file'):
        read_params_file('/dev/zero')
    with pytest.raises(ConfigError, match='directory'):
        read_params_file(tmp_path)
    big = tmp_path / 'big.yaml'
    big.write_text('/**:\n  ros__parameters:\n    robot: "' + 'x' * (9 * 1024 * 1024) + '"\n')
    with pytest.raises(ConfigError, match='larger than 8 MiB'):
        read_params_file(big)
    deep = tmp_path / 'deep.yaml'
    deep.write_text('/**:\n  ros__parameters:\n    robot: ' + '[' * 100000 + ']' * 100000 + '\n')
    with pytest.raises(ConfigError, match='nests too deeply|not valid YAML'):
        read_params_file(deep)


def test_interval_defaults_to_ending_and_an_old_calibrated_file_keeps_starting(tmp_path):
    assert OdometryConfig.from_flat({})['interval'] == 'ending'
    assert OdometryConfig.from_flat({'interval': 'midpoint'})['interval'] == 'midpoint'
    # written by calibrate before the convention existed: provenance, no interval
    old = write_params_file(tmp_path / 'old.yaml', {'model': 'ideal_dd'}, {'tool': 'x'})
    assert OdometryConfig.from_file(old)['interval'] == 'starting'
    # a hand-written file without provenance takes the default
    hand = tmp_path / 'hand.yaml'
    hand.write_text('/**:\n  ros__parameters:\n    model: ideal_dd\n')
    assert OdometryConfig.from_file(hand)['interval'] == 'ending'
    new = write_params_file(tmp_path / 'new.yaml', {'interval': 'ending'}, {'tool': 'x'})
    assert OdometryConfig.from_file(new)['interval'] == 'ending'
    with pytest.raises(ParameterError, match="'interval'.*ending, starting, midpoint"):
        OdometryConfig.from_flat({'interval': 'end'})


def test_c55_two_lags_in_a_parameters_file_are_refused(tmp_path):
    # One lag per model: writing two is refused, and a file edited by hand to name two is a
    # config error naming both and the lags to choose from.
    flat = {'wheel_radius': 0.1651, 'track_width': 0.555, 'model': 'augmented',
            'augmented.base': 'edd_symmetric', 'augmented.extensions': 'forward_lag, yaw_lag',
            'augmented.forward_lag.tau_s': 0.2, 'augmented.yaw_lag.tau_s': 0.1}
    match = "'forward_lag' and 'yaw_lag' cannot be combined"
    with pytest.raises(ParameterError, match=match):
        write_params_file(tmp_path / 'two_lags.yaml', flat, {'source': 'test'})
    path = write_params_file(tmp_path / 'one_lag.yaml',
                             dict(flat, **{'augmented.extensions': 'forward_lag'}),
                             {'source': 'test'})
    text = path.read_text()
    assert 'extensions: forward_lag\n' in text
    path.write_text(text.replace('extensions: forward_lag\n',
                                 'extensions: forward_lag, yaw_lag\n'))
    with pytest.raises(ParameterError, match=match) as err:
        OdometryConfig.from_file(path)
    assert err.value.exit_code == 2 and 'component_lags' in str(err.value)
