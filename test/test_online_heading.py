"""A reference without a heading (GNSS through navsat_transform): never learned from.

What a position-only reference (identity orientation, the rotation variances huge or left 0)
did before online.reference_heading: the learner compared the wheels' turning with a heading
that never turns, declared a change of ground every few metres and learned alpha_r = 0 (N172).
"""

import csv
import math

from nav_msgs.msg import Odometry
from node_harness import assert_replay_matches, NodeRig, RELIABLE, wall_ns
import numpy as np
import pytest
from reference_bag import write_reference_bag
from skidkin_ros.adapters.bag_reader import open_recording
from skidkin_ros.cli.main import main
from skidkin_ros.core.calibration.fitting import parameter_scales
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.odometry.config import OdometryConfig, write_params_file
from skidkin_ros.core.odometry.noise import NoiseModel
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.core.online import online_odometer
from skidkin_ros.core.online.position import MAX_POINTS, position_residuals, PositionSegment
from skidkin_ros.errors import ConfigError
from skidkin_ros.node.conversions import ns_to_stamp
from skidkin_ros.node.replay import replay_through_node
from skidkin_ros.sim.effects import make_effect
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate

FILE = {'model': 'edd_asymmetric', 'robot': 'sim',
        **{f'models.edd_asymmetric.{k}': v for k, v in DEFAULT_TRUE_PARAMS.items()},
        'models.edd_asymmetric.noise.calibrated': True, 'online.enabled': True}
# gps_common's utm_odometry and many navsat converters: the rotations' variances 99999
GNSS_COVARIANCE = np.diag([0.0004, 0.0004, 0.0016, 99999.0, 99999.0, 99999.0]).ravel()


@pytest.fixture(scope='module')
def drive():
    """Return a 60 s drive that turns, on a ground 25 % slower than the file's."""
    effect = make_effect('terrain_regime', 0.25, mode='time', switch_frac=0.0, yaw=0.1)
    return simulate(SimConfig(duration_s=60.0, seed=21, effects=(effect,)))


def _gnss(sim, variance=None, rate_hz=5.0, seed=0):
    """Positions of the truth with 2 cm of noise, no heading (identity orientation)."""
    t = np.arange(sim.start_ns, sim.end_ns, int(1e9 / rate_hz))
    truth = sim.truth_at(t)
    rng = np.random.default_rng(seed)
    n = len(t)
    return PoseTrack(t, truth.x + rng.normal(0, 0.02, n), truth.y + rng.normal(0, 0.02, n),
                     np.zeros(n), yaw_variance=None if variance is None else np.full(n, variance))


def _run(sim, reference, **more):
    odometer = online_odometer(OdometryConfig.from_flat({**FILE, **more}))
    return odometer, odometer.predict(sim.wheels, reference=reference)


def _fixed(sim):
    return Odometer.from_config(OdometryConfig.from_flat({**FILE, 'online.enabled': False})
                                ).predict(sim.wheels)


def _final_error(sim, prediction):
    return float(np.hypot(*(prediction.poses[-1, :2] - sim.truth.poses[-1, :2])))


def test_n172_a_heading_taken_as_measured_ruins_the_odometry(drive):
    """What the learner did before (online.reference_heading measured: the old behaviour)."""
    odometer, learned = _run(drive, _gnss(drive), **{'online.reference_heading': 'measured'})
    fixed = _fixed(drive)
    assert odometer.counters['online_change'] >= 2     # false 'new grounds'
    # 1.8x the fixed file's end error (C269 bounds each step)
    assert _final_error(drive, learned) > 1.5 * _final_error(drive, fixed)
    # the turning the wheels measure is taken for an error: the yaw parameters run away
    values = odometer.learner.values
    assert max(abs(values[k] / DEFAULT_TRUE_PARAMS[k] - 1.0) for k in values) > 0.3


@pytest.mark.parametrize('variance, cause', [(99999.0, 'covariance'), (0.0, 'constant'),
                                             (None, 'constant')])
def test_n173_auto_never_learns_from_a_heading_that_is_not_measured(drive, variance, cause):
    seen = []
    odometer = online_odometer(OdometryConfig.from_flat(FILE))
    odometer.learner._warn = lambda c, m, error=False: seen.append((c, m))
    got = odometer.predict(drive.wheels, reference=_gnss(drive, variance))
    counters = odometer.counters
    assert counters['online_segments'] == 0 and counters['online_change'] == 0
    summary = odometer.learner.summary()
    assert summary['reference_heading'] == f'unmeasured ({cause})'
    assert summary['state'] == 'holding' and summary['last_refusal'] == 'reference_no_heading'
    # every pose after the decision counted; the decision said once, with its cause
    assert counters['reference_no_heading'] >= len(_gnss(drive)) - 20
    said = [m for c, m in seen if c == 'reference_no_heading']
    assert len(said) == 1 and 'no measured heading' in said[0]
    assert ('yaw variance is 99999' if cause == 'covariance' else 'stayed +0.0000 rad') in said[0]
    # the odometry is the file's, bit for bit (the parameters never moved)
    assert odometer.learner.values == pytest.approx(DEFAULT_TRUE_PARAMS, rel=0, abs=0)
    assert np.array_equal(got.poses, _fixed(drive).poses)


def test_n173_a_measured_heading_is_never_taken_for_a_missing_one(drive):
    """A real heading (noisy truth, lidar-like) in auto: the same as measured, bit for bit."""
    truth = drive.truth_at(np.arange(drive.start_ns, drive.end_ns, 100_000_000))
    rng = np.random.default_rng(4)
    n = len(truth)
    reference = PoseTrack(truth.t_ns, truth.x + rng.normal(0, 0.01, n),
                          truth.y + rng.normal(0, 0.01, n), truth.yaw + rng.normal(0, 3e-3, n),
                          yaw_variance=np.full(n, 9e-6))
    auto, got = _run(drive, reference)
    measured, expected = _run(drive, reference, **{'online.reference_heading': 'measured'})
    assert auto.learner.summary()['reference_heading'] == 'auto'
    assert auto.counters['reference_no_heading'] == 0
    assert auto.counters['online_segments'] >= 10
    assert np.array_equal(got.poses, expected.poses)
    assert dict(auto.counters) == dict(measured.counters)


def test_n173_a_constant_heading_is_not_learned_from_before_the_wheels_turn():
    """Driving straight: a constant heading proves nothing yet, but is not learned from."""
    sim = simulate(SimConfig(duration_s=30.0, seed=5))
    t = np.arange(sim.start_ns, sim.end_ns, 100_000_000)
    left = np.full(len(sim.wheels), 5.0)   # the right wheel as fast as the model drives straight
    right = left * DEFAULT_TRUE_PARAMS['alpha_l'] / DEFAULT_TRUE_PARAMS['alpha_r']
    wheels = type(sim.wheels)(sim.wheels.t_ns, left, right)
    speed = 5.0 * DEFAULT_TRUE_PARAMS['alpha_l'] * SimConfig().geometry.wheel_radius
    x = (t - t[0]) * 1e-9 * speed * 0.8   # the ground is 20 % slower than the file says
    odometer = online_odometer(OdometryConfig.from_flat(FILE))
    straight = odometer.predict(wheels, reference=PoseTrack(t, x, np.zeros(len(t)),
                                                            np.full(len(t), 0.3)))
    assert abs(straight.poses[-1, 2]) < 1e-9
    assert odometer.counters['online_heading_constant'] >= 5
    assert odometer.counters['online_segments'] == 0
    assert odometer.learner.summary()['reference_heading'] == 'auto'   # not decided: no turn
    assert odometer.counters['reference_no_heading'] == 0


def test_n173_configured_unmeasured_and_a_bad_value():
    odometer = online_odometer(OdometryConfig.from_flat(
        {**FILE, 'online.reference_heading': 'unmeasured'}))
    status = odometer.reference_sample(1_000_000_000, 1.0, 2.0, 0.5)
    assert status == 'reference_no_heading'
    assert odometer.learner.summary()['reference_heading'] == 'unmeasured (configured)'
    # sensor_msgs' 'no data' (-1) on the yaw variance: not a heading either
    auto = online_odometer(OdometryConfig.from_flat(FILE))
    assert auto.reference_sample(1_000_000_000, 1.0, 2.0, 0.0, yaw_variance=-1.0) == (
        'reference_no_heading')
    assert auto.learner.summary()['reference_heading'] == 'unmeasured (covariance)'
    with pytest.raises(ConfigError, match='reference_heading.*auto, measured, unmeasured'):
        OdometryConfig.from_flat({**FILE, 'online.reference_heading': 'yes'}).online


@pytest.mark.ros
@pytest.mark.parametrize('position_only', [False, True])
def test_n174_the_node_and_predict_agree_on_a_gnss_reference(tmp_path, drive, position_only):
    path = write_params_file(tmp_path / 'gnss.yaml',
                             {**FILE, 'online.position_only': position_only}, {'source': 'test'})
    config = OdometryConfig.from_file(path)
    reference = _gnss(drive, 99999.0)
    odometer = online_odometer(config)
    expected = odometer.predict(drive.wheels, reference=reference)
    result = replay_through_node(drive.wheels, params_file=path, reference=reference,
                                 timeout_s=120.0)
    assert_replay_matches(result, expected)
    assert np.array_equal(result.pose_cov, expected.pose_covariances)
    for cause in ('reference_no_heading', 'reference_accepted', 'online_position_segments'):
        assert result.counters.get(cause, 0) == odometer.counters[cause], cause
    assert result.counters['reference_no_heading'] == len(reference)
    assert result.counters.get('online_segments', 0) == 0   # never the full-pose residual
    # learning from the positions moved the odometry; holding did not
    off = Odometer.from_config(OdometryConfig.from_flat({**config.values,
                                                         'online.enabled': False}))
    moved = np.abs(expected.poses - off.predict(drive.wheels).poses).max()
    assert (moved > 0.05) if position_only else (moved == 0.0)


def _segment(sim, reference, t_a, t_b):
    """Return a PositionSegment of the reference positions in [t_a, t_b] and the wheels."""
    pick = np.flatnonzero((reference.t_ns >= t_a) & (reference.t_ns <= t_b))
    wheels = sim.wheels
    ends, lefts, rights, dts = [0], [], [], []
    for a, b in zip(pick[:-1], pick[1:]):
        inside = (wheels.t_ns > reference.t_ns[a]) & (wheels.t_ns <= reference.t_ns[b])
        lefts.append(wheels.omega_l[inside])
        rights.append(wheels.omega_r[inside])
        dts.append(np.full(inside.sum(), 0.05))
        ends.append(ends[-1] + int(inside.sum()))
    return PositionSegment(np.stack([reference.x[pick], reference.y[pick]], axis=1),
                           np.concatenate(lefts), np.concatenate(rights), np.concatenate(dts),
                           np.array(ends), 0.0)


def test_c273_the_position_residual_ignores_the_frame_and_sees_only_the_shape():
    """The residual of positions alone: zero at the truth, blind to the heading and place."""
    sim = simulate(SimConfig(duration_s=20.0, seed=7))
    model = get_model('edd_asymmetric')
    geometry = sim.config.geometry
    k = model.vector(DEFAULT_TRUE_PARAMS, geometry)
    scale = parameter_scales(model, geometry)
    mount = (0.3, 0.1)
    truth = sim.truth_at(sim.wheels.t_ns[::4])
    c, s = np.cos(truth.yaw), np.sin(truth.yaw)
    antenna = PoseTrack(truth.t_ns, truth.x + c * 0.3 - s * 0.1, truth.y + s * 0.3 + c * 0.1,
                        np.zeros(len(truth)))
    seg = _segment(sim, antenna, truth.t_ns[2], truth.t_ns[14])
    noise = NoiseModel(1e-3, 1e-3, 1e-4, 1e-3)
    errors, sens = position_residuals(model, k, geometry, [seg], mount, scale, noise, 0.02)
    assert errors.shape == (1, 2 * MAX_POINTS) and sens.shape == (1, 2 * MAX_POINTS, 5)
    # the simulator integrates its own way: the residual is a small fraction of one sigma
    assert np.abs(errors).max() < 0.3
    # the same positions turned by 1 rad and moved 100 m: the same residual (no heading used)
    turn = np.array([[math.cos(1.0), -math.sin(1.0)], [math.sin(1.0), math.cos(1.0)]])
    moved = PositionSegment(seg.u @ turn.T + [100.0, -50.0], seg.left, seg.right, seg.dt_s,
                            seg.ends, 0.0)
    errors_moved, sens_moved = position_residuals(model, k, geometry, [moved], mount, scale,
                                                  noise, 0.02)
    np.testing.assert_allclose(errors_moved, errors, atol=1e-6)
    np.testing.assert_allclose(sens_moved, sens, atol=1e-6)
    # a wrong speed scale (alpha 10 % high) shows: the path is too long for the positions
    wrong = k.copy()
    wrong[:2] *= 1.1
    errors_wrong, _ = position_residuals(model, wrong, geometry, [seg], mount, scale, noise,
                                         0.02)
    assert np.linalg.norm(errors_wrong) > 3.0 * np.linalg.norm(errors)
    # driving straight says nothing of the yaw parameters (the ICR's y_l, y_r)
    straight = PositionSegment(np.stack([np.arange(9) * 0.05, np.zeros(9)], axis=1),
                               np.full(80, 3.0), np.full(80, 3.0 * k[0] / k[1]),
                               np.full(80, 0.05), np.arange(0, 81, 10), 0.0)
    _, sens_straight = position_residuals(model, k, geometry, [straight], (0.0, 0.0), scale,
                                          noise, 0.02)
    info = sens_straight[0].T @ sens_straight[0]
    names = list(model.param_names)
    for name in ('y_l', 'y_r'):
        assert info[names.index(name), names.index(name)] < 1e-6 * np.trace(info)


def test_c274_position_only_learns_the_speed_of_a_new_ground(drive):
    """A 25 % slower ground from a 5 Hz GNSS antenna 0.3 m ahead: alpha learned, no heading."""
    t = np.arange(drive.start_ns, drive.end_ns, 200_000_000)
    truth = drive.truth_at(t)
    rng = np.random.default_rng(3)
    n = len(t)
    c, s = np.cos(truth.yaw), np.sin(truth.yaw)
    antenna = PoseTrack(t, truth.x + 0.3 * c + rng.normal(0, 0.02, n),
                        truth.y + 0.3 * s + rng.normal(0, 0.02, n), np.zeros(n),
                        yaw_variance=np.full(n, 99999.0))
    odometer, got = _run(drive, antenna, **{'online.position_only': True,
                                            'online.mount_x': 0.3})
    counters = odometer.counters
    assert counters['online_position_segments'] >= 3 and counters['online_segments'] == 0
    values = odometer.learner.values
    for name in ('alpha_l', 'alpha_r'):   # most of the way from the file's to the truth's
        share = (DEFAULT_TRUE_PARAMS[name] - values[name]) / (0.25 * DEFAULT_TRUE_PARAMS[name])
        assert 0.6 < share < 1.2, (name, share)
    assert odometer.learner.summary()['state'] == 'learning'
    assert _final_error(drive, got) < 0.7 * _final_error(drive, _fixed(drive))


def _gnss_msg(t_ns, x, y, covariance):
    msg = Odometry()
    msg.header.stamp = ns_to_stamp(t_ns)
    msg.header.frame_id = 'utm'
    msg.child_frame_id = 'gps'
    msg.pose.pose.position.x = float(x)
    msg.pose.pose.position.y = float(y)
    msg.pose.pose.orientation.w = 1.0   # identity: no heading
    msg.pose.covariance = [float(v) for v in covariance]
    return msg


@pytest.mark.ros
@pytest.mark.parametrize('covariance, cause', [(GNSS_COVARIANCE, 'covariance'),
                                               (np.zeros(36), 'constant')])
def test_n175_a_real_node_fed_navsat_odometry_says_why_it_does_not_learn(covariance, cause):
    """The node turning in place while a GNSS reference (identity orientation) comes in."""
    rig = NodeRig(FILE)
    try:
        ref_pub = rig.driver.create_publisher(Odometry, 'reference/odom', RELIABLE)
        rig.wait_matched(ref_pub)
        t0 = wall_ns() - 30 * 1_000_000_000
        # the receiver's 2 cm of noise: a pose repeated whole is a frozen reference (N188)
        noise = np.random.default_rng(2).normal(0.0, 0.02, (30, 2))
        for i in range(120):   # 6 s at 20 Hz, turning left about 0.5 rad/s
            t = t0 + i * 50_000_000
            rig.send_joint(t, -2.0, 2.0)
            if i % 4 == 0:   # 5 Hz, the robot turns on the spot
                before = rig.node.counters['reference_received']
                ref_pub.publish(_gnss_msg(t, 10.0 + noise[i // 4, 0], 5.0 + noise[i // 4, 1],
                                          covariance))
                rig.spin_until(lambda: rig.node.counters['reference_received'] > before,
                               what='reference pose')
        rig.drain()
        counters = rig.node.counters
        assert counters['published'] == 120 == len(rig.odom)
        assert counters['reference_no_heading'] >= (30 if cause == 'covariance' else 20)
        assert counters['online_segments'] == 0
        values = {kv.key: kv.value for kv in rig.node.diagnostic_status().values}
        assert values['online.reference_heading'] == f'unmeasured ({cause})'
        assert values['online.state'] == 'holding'
        assert int(values['count.reference_no_heading']) == counters['reference_no_heading']
        assert 'no measured heading' in rig.node.last_warnings['reference_no_heading']
        # the odometry turned as the wheels say, with the file's parameters
        assert math.isfinite(rig.odom[-1].pose.pose.position.x)
    finally:
        rig.close()


def test_c272_predict_reads_the_yaw_variance_of_a_bags_gnss_odometry(tmp_path, capsys):
    effect = make_effect('terrain_regime', 0.25, mode='time', switch_frac=0.0, yaw=0.1)
    sim = simulate(SimConfig(duration_s=40.0, seed=22, effects=(effect,)))
    gnss = _gnss(sim, rate_hz=5.0)
    bag = write_reference_bag(tmp_path / 'gnss', sim.wheels, '/odometry/gps', gnss, 'utm', 'gps',
                              lambda j: GNSS_COVARIANCE)   # _gnss: heading 0 throughout
    with open_recording(bag) as recording:
        track = recording.read_pose_track('/odometry/gps')
    assert np.array_equal(track.yaw_variance, np.full(len(track), 99999.0))
    params = write_params_file(tmp_path / 'file.yaml', FILE, {'source': 'test'})
    out, fixed_out = tmp_path / 'pred.csv', tmp_path / 'fixed.csv'
    assert main(['predict', str(bag), '--params', str(params), '--reference', '/odometry/gps',
                 '--out', str(out)]) == 0
    assert '0 segments, last state holding' in capsys.readouterr().out
    no_online = write_params_file(tmp_path / 'off.yaml', {**FILE, 'online.enabled': False},
                                  {'source': 'test'})
    assert main(['predict', str(bag), '--params', str(no_online), '--out', str(fixed_out)]) == 0
    with out.open() as a, fixed_out.open() as b:
        rows, fixed = list(csv.DictReader(a)), list(csv.DictReader(b))
    assert [(r['x'], r['y'], r['yaw']) for r in rows] == [(r['x'], r['y'], r['yaw'])
                                                          for r in fixed]
