"""The reference-heading rule and position-only learning against a careful reviewer's inputs.

A real heading never taken for a missing one (a SLAM frozen while the robot turns, a localizer
whose yaw variance is huge for a while), a converter's constant heading never taken for a real
one (jittering at float32's size), a wrong antenna mount never learned from (fault rows
N188-N190, C285-C286).
"""

import csv
import math

from node_harness import assert_replay_matches
import numpy as np
import pytest
from reference_bag import write_reference_bag
from skidkin_ros.adapters.bag_reader import open_recording
from skidkin_ros.cli.main import main
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.core.odometry.config import OdometryConfig, write_params_file
from skidkin_ros.core.online import online_odometer
from skidkin_ros.core.rotation import quaternion_to_yaw, yaw_to_quaternion
from skidkin_ros.node.replay import replay_through_node
from skidkin_ros.sim.effects import make_effect
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate
from test_online_heading import _final_error, _fixed, _gnss, _run, FILE


@pytest.fixture(scope='module')
def drive():
    """Return a 60 s drive that turns, on a ground 25 % slower than the file's."""
    effect = make_effect('terrain_regime', 0.25, mode='time', switch_frac=0.0, yaw=0.1)
    return simulate(SimConfig(duration_s=60.0, seed=21, effects=(effect,)))


def _slam(sim, seed=4):
    """Return a lidar-like reference at 10 Hz: the truth with 1 cm and 3 mrad of noise."""
    truth = sim.truth_at(np.arange(sim.start_ns, sim.end_ns, 100_000_000))
    rng = np.random.default_rng(seed)
    n = len(truth)
    return PoseTrack(truth.t_ns, truth.x + rng.normal(0, 0.01, n),
                     truth.y + rng.normal(0, 0.01, n), truth.yaw + rng.normal(0, 3e-3, n))


def test_n188_a_slam_frozen_while_the_robot_turns_is_not_a_missing_heading(drive):
    """Lost for 6 s (the pose repeated whole) while the robot turned 2.6 rad: a stall."""
    slam = _slam(drive)
    x, y, yaw = slam.x.copy(), slam.y.copy(), slam.yaw.copy()
    x[200:260], y[200:260], yaw[200:260] = x[200], y[200], yaw[200]
    truth = drive.truth_at(slam.t_ns[200:260])
    assert np.ptp(np.unwrap(truth.yaw)) > 1.0   # the robot did turn meanwhile
    odometer, got = _run(drive, PoseTrack(slam.t_ns, x, y, yaw))
    # it was taken for a GNSS's constant heading, for good: nothing learned after it
    assert odometer.learner.summary()['reference_heading'] == 'auto'
    assert odometer.counters['reference_no_heading'] == 0
    assert odometer.counters['online_segments'] >= 15
    assert _final_error(drive, got) < 0.5 * _final_error(drive, _fixed(drive))


def _lost_then_found(sim):
    """Return AMCL after a global localization: the yaw variance 3.3 rad^2 for 2 s, then 0.01."""
    slam = _slam(sim)
    variance = np.full(len(slam), 0.01)
    variance[:20] = 3.3
    return PoseTrack(slam.t_ns, slam.x, slam.y, slam.yaw, yaw_variance=variance)


def test_n189_a_localizer_lost_for_a_while_has_its_heading_measured_again(drive):
    seen = []
    odometer = online_odometer(OdometryConfig.from_flat(FILE))
    odometer.learner._warn = lambda c, m, error=False: seen.append(c)
    got = odometer.predict(drive.wheels, reference=_lost_then_found(drive))
    counters = odometer.counters
    assert odometer.learner.summary()['reference_heading'] == 'auto'
    # the 20 lost poses and the 4 before the 5th measured one in a row: not learned from
    assert counters['reference_no_heading'] == 24
    assert seen.count('reference_no_heading') == 1
    assert seen.count('reference_heading_measured') == 1
    assert counters['online_segments'] >= 15     # was 0: unmeasured for good
    assert _final_error(drive, got) < 0.5 * _final_error(drive, _fixed(drive))


def test_n189_a_yaw_variance_that_alternates_stays_unmeasured(drive):
    """Huge every other pose (two publishers?): never measured again, positions learned."""
    gnss = _gnss(drive)
    variance = np.where(np.arange(len(gnss)) % 2, 99999.0, 0.01)
    odometer, got = _run(drive, PoseTrack(gnss.t_ns, gnss.x, gnss.y, gnss.yaw,
                                          yaw_variance=variance), **{'online.position_only': True})
    assert odometer.learner.summary()['reference_heading'] == 'unmeasured (covariance)'
    assert odometer.counters['online_segments'] == 0
    assert odometer.counters['online_position_segments'] >= 2
    assert np.isfinite(got.poses).all()


@pytest.mark.ros
@pytest.mark.parametrize('position_only', [False, True])
def test_n189_the_node_and_predict_agree_when_the_heading_comes_back(tmp_path, drive, capsys,
                                                                     position_only):
    """A real bag (rosbags) of AMCL-style odometry: `skidkin predict` and the node, bit for bit."""
    reference = _lost_then_found(drive)

    def covariance(j):
        values = np.zeros(36)
        values[35] = reference.yaw_variance[j]
        return values

    bag = write_reference_bag(tmp_path / 'amcl', drive.wheels, '/amcl/odom', reference, 'map',
                              'base_link', covariance)
    with open_recording(bag) as recording:
        track = recording.read_pose_track('/amcl/odom')
    assert np.array_equal(track.yaw_variance, reference.yaw_variance)
    path = write_params_file(tmp_path / 'amcl.yaml',
                             {**FILE, 'online.position_only': position_only}, {'source': 'test'})
    out = tmp_path / 'pred.csv'
    assert main(['predict', str(bag), '--params', str(path), '--reference', '/amcl/odom',
                 '--out', str(out)]) == 0
    odometer = online_odometer(OdometryConfig.from_file(path))
    expected = odometer.predict(drive.wheels, reference=track)
    with out.open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == len(expected.poses)
    np.testing.assert_allclose([[float(r['x']), float(r['y'])] for r in rows],
                               expected.poses[:, :2], rtol=0, atol=1e-6)
    # the harness sends the track's yaw through one more quaternion: predict gets it too
    wire_yaw = np.array([quaternion_to_yaw(*yaw_to_quaternion(float(v))) for v in track.yaw])
    odometer = online_odometer(OdometryConfig.from_file(path))
    expected = odometer.predict(drive.wheels, reference=PoseTrack(
        track.t_ns, track.x, track.y, wire_yaw, yaw_variance=track.yaw_variance))
    result = replay_through_node(drive.wheels, params_file=path, reference=track,
                                 timeout_s=120.0)
    assert_replay_matches(result, expected)
    assert np.array_equal(result.pose_cov, expected.pose_covariances)
    for cause in ('reference_no_heading', 'reference_accepted', 'online_segments',
                  'online_position_segments'):
        assert result.counters.get(cause, 0) == odometer.counters[cause], cause
    assert result.counters['online_segments'] >= 15
    assert result.counters['reference_no_heading'] == 24


def test_n190_a_constant_heading_jittering_at_float32_size_is_not_measured(drive):
    """A converter's constant passed through float32 math: 1e-7 rad of jitter, variance 0."""
    gnss = _gnss(drive, 0.0, rate_hz=10.0)
    jitter = np.random.default_rng(3).normal(0.0, 1e-7, len(gnss))
    odometer, got = _run(drive, PoseTrack(gnss.t_ns, gnss.x, gnss.y, jitter,
                                          yaw_variance=gnss.yaw_variance))
    # it was taken as measured: 6 segments learned, end error 2.8 m against the file's 1.4 m
    assert odometer.learner.summary()['reference_heading'] == 'unmeasured (constant)'
    assert odometer.counters['online_segments'] == 0
    assert odometer.learner.values == pytest.approx(DEFAULT_TRUE_PARAMS, rel=0, abs=0)
    assert np.array_equal(got.poses, _fixed(drive).poses)


def test_c285_position_only_never_learns_from_an_antenna_mount_far_off(drive):
    """online.mount_x 5 m where the antenna is on the axis: a turn's positions cannot fit."""
    seen = []
    odometer = online_odometer(OdometryConfig.from_flat(
        {**FILE, 'online.position_only': True, 'online.mount_x': 5.0}))
    odometer.learner._warn = lambda c, m, error=False: seen.append(m)
    got = odometer.predict(drive.wheels, reference=_gnss(drive, 99999.0))
    assert odometer.counters['online_inconsistent'] >= 1
    assert any('mount_x/y wrong?' in m for m in seen)
    # it learned the wrong lever: end error 11.3 m against the file's 1.41 m
    assert _final_error(drive, got) < 1.1 * _final_error(drive, _fixed(drive))


def test_c286_position_only_survives_the_worst_positions(drive):
    """NaN, 5 m multipath jumps and a reference stuck while the wheels spin, in one drive."""
    gnss = _gnss(drive, 99999.0)
    x, y = gnss.x.copy(), gnss.y.copy()
    x[50:60] = math.nan
    x[100:103] += 5.0
    x[205:215] += 5.0
    x[240:280], y[240:280] = x[240], y[240]
    odometer, got = _run(drive, PoseTrack(gnss.t_ns, x, y, gnss.yaw,
                                          yaw_variance=gnss.yaw_variance),
                         **{'online.position_only': True})
    counters = odometer.counters
    assert np.isfinite(got.poses).all() and np.isfinite(got.pose_covariances).all()
    assert np.isfinite(odometer.learner.k).all()
    assert len(got.poses) == len(drive.wheels)   # never stopped
    assert counters['reference_non_finite'] == 10
    assert counters['reference_jump'] >= 10 and counters['reference_stall'] >= 10
    assert counters['online_position_segments'] >= 1
