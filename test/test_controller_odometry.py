"""A drive controller's odometry as the wheel input, and other ground-truth and wheel-less bags.

The rule (diff_drive_controller's twist from wheel speeds, inverted) has one home,
core/odometry/controller.py; the bag reader, predict and the node run it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from skidkin_ros.adapters.bag_reader import open_recording
from skidkin_ros.adapters.bag_writer import BagWriter
from skidkin_ros.cli.main import main
from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.core.odometry.config import OdometryConfig, read_params_file
from skidkin_ros.core.odometry.controller import ControllerGeometry, NonFiniteTwistError
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.errors import ParameterError, RecordingError
from skidkin_ros.sim.simulate import SimConfig, simulate

# The controller's own configuration: deliberately not the robot's geometry (0.1651, 0.555).
CONTROLLER = ControllerGeometry(0.16, 0.5, 1.03, 0.97, 1.2)
MULTIPLIERS = ['1.03', '0.97', '1.2']
MODELS = ('edd_symmetric', 'edd_asymmetric')


def test_the_rule_inverts_diff_drive_controllers_twist():
    rng = np.random.default_rng(1)
    for omega_l, omega_r in rng.uniform(-8, 8, (50, 2)):
        v, w = CONTROLLER.twist(omega_l, omega_r)
        back = CONTROLLER.wheel_speeds(v, w)
        assert back == pytest.approx((omega_l, omega_r), rel=1e-13, abs=1e-13)
    # By hand: r_l = 0.1648, r_r = 0.1552, b = 0.6; straight 1 m/s, then a pure turn.
    assert CONTROLLER.wheel_speeds(1.0, 0.0) == pytest.approx((1 / 0.1648, 1 / 0.1552))
    assert CONTROLLER.wheel_speeds(0.0, 1.0) == pytest.approx((-0.3 / 0.1648, 0.3 / 0.1552))


@pytest.mark.parametrize('v, w', [(math.nan, 0.0), (0.1, math.inf), (-math.inf, math.nan)])
def test_c112_a_non_finite_twist_is_refused_by_the_rule(v, w):
    with pytest.raises(NonFiniteTwistError, match='not finite'):
        CONTROLLER.wheel_speeds(v, w)


def test_c113_the_odometry_input_without_the_controller_geometry_is_a_clear_error():
    with pytest.raises(ParameterError) as err:
        OdometryConfig.from_flat({'input': 'odometry'})
    text = str(err.value)
    assert 'controller.wheel_radius' in text and 'controller.wheel_separation' in text
    assert 'ros2 param get' in text
    with pytest.raises(ParameterError, match='controller.wheel_separation'):
        OdometryConfig.from_flat({'input': 'odometry', 'controller.wheel_radius': 0.1})
    with pytest.raises(ParameterError, match='wheel_signal'):
        OdometryConfig.from_flat({'input': 'odometry', 'controller.wheel_radius': 0.1,
                                  'controller.wheel_separation': 0.5,
                                  'wheel_signal': 'position'})
    config = OdometryConfig.from_flat({'input': 'odometry', **CONTROLLER.as_values()})
    assert ControllerGeometry.from_values(config.values) == CONTROLLER


def test_n80_the_odometer_refuses_a_non_finite_twist_and_integrates_the_rest():
    config = OdometryConfig.from_flat({'input': 'odometry', **CONTROLLER.as_values()})
    odometer = Odometer.from_config(config)
    t0 = 1_000_000_000_000
    now = t0 + 10**9
    assert odometer.twist_sample(t0, 0.5, 0.1, now) is not None
    assert odometer.twist_sample(t0 + 20_000_000, math.nan, 0.1, now) is None
    assert odometer.counters['non_finite_twist'] == 1
    estimate = odometer.twist_sample(t0 + 40_000_000, 0.5, 0.1, now)
    assert estimate is not None and np.all(np.isfinite(estimate.pose))


def _drive_bags(tmp_path, sim):
    """Write the same drive twice: as JointState and as a controller's Odometry; AMCL truth."""
    joint_bag, odom_bag = tmp_path / 'joint_state', tmp_path / 'controller_odom'
    wheels, truth = sim.wheels, sim.truth
    with BagWriter(joint_bag) as a, BagWriter(odom_bag, storage='mcap') as b:
        x = y = yaw = 0.0
        previous = None
        for i, t_ns in enumerate(wheels.t_ns.tolist()):
            wl, wr = float(wheels.omega_l[i]), float(wheels.omega_r[i])
            a.write_joint_state('/joint_states', t_ns, ['left_wheel', 'right_wheel'], [wl, wr])
            v, w = CONTROLLER.twist(wl, wr)
            if previous is not None:  # the controller's own pose (not read by skidkin)
                dt = (t_ns - previous) * 1e-9
                x, y, yaw = (x + v * dt * math.cos(yaw), y + v * dt * math.sin(yaw),
                             yaw + w * dt)
            previous = t_ns
            b.write_odometry('/odom', t_ns, 'odom', 'base_link', x, y, yaw, twist=(v, w))
            for bag in (a, b):
                bag.write_pose_with_covariance('/amcl_pose', t_ns, 'map', truth.x[i], truth.y[i],
                                               truth.yaw[i], covariance=np.eye(6).ravel() * 0.01)
    return joint_bag, odom_bag


@pytest.fixture(scope='module')
def drive(tmp_path_factory):
    sim = simulate(SimConfig(duration_s=90.0, seed=5))
    return _drive_bags(tmp_path_factory.mktemp('controller'), sim)


def test_the_recovered_speeds_are_the_recorded_ones(drive):
    joint_bag, odom_bag = drive
    with open_recording(joint_bag) as a, open_recording(odom_bag) as b:
        wa = a.read_wheels()
        wb = b.read_wheels(controller=CONTROLLER)
        assert b.wheel_input['input'] == 'odometry' and b.wheel_input['topic'] == '/odom'
        track = b.read_pose_track('/amcl_pose')
    np.testing.assert_array_equal(wa.t_ns, wb.t_ns)
    np.testing.assert_allclose(wb.omega_l, wa.omega_l, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(wb.omega_r, wa.omega_r, rtol=1e-12, atol=1e-12)
    assert len(track.t_ns) == len(wa.t_ns)


def _fitted(path):
    flat = read_params_file(path)
    out = {}
    for model in MODELS:
        names = sorted(k for k in flat if k.startswith(f'models.{model}.')
                       and k.count('.') == 2 and not k.endswith('parameter_covariance'))
        values = np.array([flat[k] for k in names])
        size = len(names)
        cov = np.array(flat[f'models.{model}.parameter_covariance']).reshape(size, size)
        out[model] = (names, values, np.sqrt(np.diag(cov)))
    return flat, out


@pytest.mark.heavy
def test_a_drive_recorded_as_controller_odometry_calibrates_to_the_jointstate_model(
        drive, tmp_path, capsys):
    joint_bag, odom_bag = drive
    common = ['--ground-truth', '/amcl_pose', '--models', *MODELS, '--starts', '2']
    pa, pb, pw = tmp_path / 'a.yaml', tmp_path / 'b.yaml', tmp_path / 'wrong.yaml'
    assert main(['calibrate', str(joint_bag), '--out', str(pa)] + common) == 0
    assert main(['calibrate', str(odom_bag), '--out', str(pb), '--wheel-odometry', '/odom',
                 '--controller-geometry', '0.16', '0.5', '--controller-multipliers',
                 *MULTIPLIERS] + common) == 0
    # Without the controller's multipliers the recovered speeds are off by 3 %: a wrong model.
    assert main(['calibrate', str(odom_bag), '--out', str(pw), '--wheel-odometry', '/odom',
                 '--controller-geometry', '0.16', '0.5'] + common) == 0
    _, a = _fitted(pa)
    flat_b, b = _fitted(pb)
    _, wrong = _fitted(pw)
    for model in MODELS:
        names, va, sa = a[model]
        _, vb, sb = b[model]
        assert np.all(sa > 0)
        assert np.all(np.abs(va - vb) <= 0.01 * sa), (model, names, va, vb, sa)
        assert np.any(np.abs(va - wrong[model][1]) > 2 * sa), (model, names)
    # The parameters file tells the node to read the controller's odometry the same way.
    assert flat_b['input'] == 'odometry'
    assert ControllerGeometry.from_values(flat_b) == CONTROLLER
    pred = tmp_path / 'pred.csv'
    assert main(['predict', str(odom_bag), '--params', str(pb), '--out', str(pred)]) == 0
    capsys.readouterr()
    assert main(['predict', str(odom_bag), '--params', str(pb), '--out', str(pred), '--force',
                 '--controller-geometry', '0.2', '0.5']) != 0
    assert 'differ from the controller.*' in capsys.readouterr().err


def _odometry_only_bag(path, with_lidar=False):
    """Only what many robots record: the controller's /odom, /tf, /tf_static, /amcl_pose."""
    t0 = 1_700_000_000_000_000_000
    with BagWriter(path, storage='mcap') as bag:
        bag.write_tf_static(t0, 'base_link', 'lidar', [0.2, 0.0, 0.4], [0.0, 0.0, 0.0, 1.0])
        for i in range(40):
            t = t0 + i * 50_000_000
            bag.write_odometry('/odom', t, 'odom', 'base_link', 0.01 * i, 0.0, 0.0,
                               twist=(0.2, 0.0))
            bag.write_pose_with_covariance('/amcl_pose', t, 'map', 0.01 * i, 0.0, 0.0)
    return path


def test_c113_an_odometry_only_bag_says_how_to_use_the_controller_odometry(tmp_path, capsys):
    bag = _odometry_only_bag(tmp_path / 'odom_only')
    code = main(['calibrate', str(bag), '--out', str(tmp_path / 'p.yaml'),
                 '--ground-truth', '/amcl_pose'])
    err = capsys.readouterr().err
    assert code != 0 and 'Traceback' not in err
    assert '/odom' in err and '--wheel-odometry' in err and '--controller-geometry' in err
    code = main(['calibrate', str(bag), '--out', str(tmp_path / 'p.yaml'),
                 '--ground-truth', '/amcl_pose', '--wheel-odometry', '/odom'])
    err = capsys.readouterr().err
    assert code != 0 and 'Traceback' not in err and "controller's own geometry" in err
    with open_recording(bag) as rec:
        with pytest.raises(RecordingError, match='--controller-geometry'):
            rec.read_wheels(odometry_topic='/odom')


def test_c112_twists_with_nan_are_dropped_and_counted_offline(tmp_path):
    path = tmp_path / 'nan'
    t0 = 1_700_000_000_000_000_000
    with BagWriter(path) as bag:
        for i in range(30):
            twist = (math.nan, 0.0) if i in (7, 8) else (0.3, 0.1)
            bag.write_odometry('/odom', t0 + i * 20_000_000, 'odom', 'base_link', 0.0, 0.0, 0.0,
                               twist=twist)
    with open_recording(path) as rec:
        wheels = rec.read_wheels(controller=CONTROLLER)
        notes = ' '.join(rec.notes)
    assert len(wheels) == 28 and '2 non-finite twist' in notes
    assert np.all(np.isfinite(wheels.omega_l)) and np.all(np.isfinite(wheels.omega_r))


def test_pose_with_covariance_stamped_is_a_ground_truth_beside_odometry_and_pose(tmp_path):
    path = tmp_path / 'truths'
    t0 = 1_700_000_000_000_000_000
    with BagWriter(path) as bag:
        for i in range(20):
            t = t0 + i * 100_000_000
            yaw = 0.4 * i
            bag.write_odometry('/odometry/filtered', t, 'odom', 'base_link', 0.1 * i, -0.05 * i,
                               yaw)
            bag.write_pose_stamped('/pose', t, 'map', 0.1 * i, -0.05 * i, yaw)
            bag.write_pose_with_covariance('/amcl_pose', t, 'map', 0.1 * i, -0.05 * i, yaw)
    with open_recording(path) as rec:
        tracks = [rec.read_pose_track(topic)
                  for topic in ('/odometry/filtered', '/pose', '/amcl_pose')]
        with pytest.raises(RecordingError, match='several'):
            rec.read_pose_track()  # three candidates: name one
    for track in tracks[1:]:
        for name in ('t_ns', 'x', 'y', 'yaw'):
            np.testing.assert_array_equal(getattr(track, name), getattr(tracks[0], name))
    assert tracks[0].yaw[-1] == pytest.approx(0.4 * 19)  # unwrapped


def test_predict_refuses_controller_options_for_a_jointstate_parameters_file(
        drive, tmp_path, capsys):
    joint_bag, _ = drive
    params = tmp_path / 'p.yaml'
    params.write_text('/**:\n  ros__parameters:\n    model: ideal_dd\n')
    code = main(['predict', str(joint_bag), '--params', str(params), '--out',
                 str(tmp_path / 'o.csv'), '--controller-geometry', '0.16', '0.5'])
    err = capsys.readouterr().err
    assert code != 0 and 'not odometry' in err and 'Traceback' not in err


def test_recovered_speeds_run_through_predict_as_the_node_would(drive):
    _, odom_bag = drive
    config = OdometryConfig.from_flat({'input': 'odometry', **CONTROLLER.as_values()})
    with open_recording(odom_bag) as rec:
        wheels = rec.read_wheels(controller=ControllerGeometry.from_values(config.values))
        twists = [(stamp, msg.twist.twist.linear.x, msg.twist.twist.angular.z)
                  for stamp, msg in rec.messages('/odom')]
    offline = Odometer.from_config(config).predict(wheels)
    live = Odometer.from_config(config)
    live.reset()
    for t_ns, v, w in twists:
        live.twist_sample(t_ns, v, w, t_ns)
    np.testing.assert_array_equal(live.pose, offline.poses[-1])
    assert isinstance(wheels, WheelSamples)
