"""Online calibration judged by the gyro: a reference that turns where the gyro does not pauses."""

import dataclasses

import numpy as np
import pytest
from skidkin_ros.core.drive import PoseTrack, WheelSamples
from skidkin_ros.core.odometry.config import OdometryConfig, write_params_file
from skidkin_ros.core.online import online_odometer
from skidkin_ros.core.rotation import quaternion_to_yaw, yaw_to_quaternion
from skidkin_ros.errors import ConfigError
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate

FILE = {'model': 'edd_asymmetric', 'robot': 'sim',
        **{f'models.edd_asymmetric.{k}': v for k, v in DEFAULT_TRUE_PARAMS.items()},
        'models.edd_asymmetric.noise.calibrated': True, 'online.enabled': True}
SPURIOUS_RAD = 0.015   # per 0.1 s reference interval: 0.15 rad/s the gyro does not see


def _reference(sim, bad_from_s=None, bad_to_s=None):
    """Return the truth at 10 Hz; between the two times, a heading drift the robot lacks.

    The drift is composed into the reference's own trajectory (its positions follow its wrong
    heading), as a lidar odometry that degenerates in yaw would publish it.
    """
    t = np.arange(sim.start_ns, sim.end_ns, 100_000_000)
    truth = sim.truth_at(t)
    if bad_from_s is None:
        return truth
    rel = (t - sim.start_ns) * 1e-9
    x, y, yaw = [truth.x[0]], [truth.y[0]], [truth.yaw[0]]
    for i in range(1, len(t)):
        c, s = np.cos(truth.yaw[i - 1]), np.sin(truth.yaw[i - 1])
        dx, dy = truth.x[i] - truth.x[i - 1], truth.y[i] - truth.y[i - 1]
        bx, by = c * dx + s * dy, c * dy - s * dx
        turn = truth.yaw[i] - truth.yaw[i - 1]
        if bad_from_s <= rel[i] < bad_to_s:
            turn += SPURIOUS_RAD
        c, s = np.cos(yaw[-1]), np.sin(yaw[-1])
        x.append(x[-1] + c * bx - s * by)
        y.append(y[-1] + s * bx + c * by)
        yaw.append(yaw[-1] + turn)
    return PoseTrack(t, np.array(x), np.array(y), np.array(yaw))


@pytest.fixture(scope='module')
def drive():
    return simulate(SimConfig(duration_s=80.0, seed=3))


def _learn(sim, reference, imu_mode):
    odometer = online_odometer(OdometryConfig.from_flat({**FILE, 'imu.mode': imu_mode}))
    odometer.predict(sim.wheels, reference=reference,
                     imu=sim.imu if imu_mode != 'off' else None)
    return odometer


def test_a_good_reference_is_never_refused_by_the_gyro(drive):
    with_gyro = _learn(drive, _reference(drive), 'fuse')
    without = _learn(drive, _reference(drive), 'off')
    assert with_gyro.counters['reference_gyro'] == 0
    assert with_gyro.counters['online_segments'] == without.counters['online_segments'] > 20
    # the same to 1e-5: the reference's measured heading noise (refnoise.py: the mean of the
    # squares sees the model's small changing error) is taken against the fused rotation
    assert with_gyro.learner.values == pytest.approx(without.learner.values, rel=1e-5)


def test_a_reference_turning_where_the_gyro_does_not_pauses_learning(drive):
    bad = _reference(drive, 40.0, 80.0)
    judged = _learn(drive, bad, 'fuse')
    blind = _learn(drive, bad, 'off')
    good = _learn(drive, _reference(drive), 'fuse')
    counters = judged.counters
    assert counters['reference_gyro'] >= 50
    summary = judged.learner.summary()
    assert summary['last_refusal'] == 'reference_gyro'
    assert summary['state'] == 'holding' and blind.learner.summary()['state'] != 'holding'
    # learning paused: no segment of the bad half was learned, no false change of ground
    assert counters['online_segments'] < 0.6 * good.counters['online_segments']
    assert counters['online_change'] == 0 < blind.counters['online_change']
    truth = np.array([DEFAULT_TRUE_PARAMS[k] for k in ('alpha_l', 'alpha_r', 'y_l', 'y_r')])

    def error(odometer):
        values = odometer.learner.values
        return np.abs(np.array([values[k] for k in ('alpha_l', 'alpha_r', 'y_l', 'y_r')])
                      / truth - 1).max()
    # without the gyro the drifting reference taught wrong values (5 % to 24 % on variants of
    # this drive); with it, the values of the good half stay
    assert error(judged) < 0.03 < error(blind)


def test_adapt_with_online_stays_refused_with_the_reason():
    with pytest.raises(ConfigError, match='imu.mode fuse'):
        OdometryConfig.from_flat({**FILE, 'imu.mode': 'adapt'})


@pytest.mark.ros
def test_the_node_refuses_a_reference_the_gyro_contradicts_as_predict_does(tmp_path):
    from skidkin_ros.node.replay import replay_through_node
    sim = simulate(SimConfig(duration_s=40.0, seed=4))
    keep = sim.wheels.t_ns <= sim.imu.t_ns[-1] - 100_000_000   # the gyro outlasts the wheels
    wheels = WheelSamples(sim.wheels.t_ns[keep], sim.wheels.omega_l[keep],
                          sim.wheels.omega_r[keep])
    path = write_params_file(tmp_path / 'online.yaml', {**FILE, 'imu.mode': 'fuse'},
                             {'source': 'test'})
    reference = _reference(sim, 20.0, 40.0)
    wire_yaw = [quaternion_to_yaw(*yaw_to_quaternion(float(v))) for v in reference.yaw]
    odometer = online_odometer(OdometryConfig.from_file(path))
    expected = odometer.predict(wheels, imu=sim.imu, reference=PoseTrack(
        reference.t_ns, reference.x, reference.y, np.array(wire_yaw)))
    result = replay_through_node(wheels, params_file=path, imu=sim.imu,
                                 reference=reference, timeout_s=120.0)
    assert odometer.counters['reference_gyro'] >= 20
    for cause in ('reference_gyro', 'online_segments', 'reference_accepted'):
        assert result.counters.get(cause, 0) == odometer.counters[cause], cause
    assert len(result) == len(wheels)
    assert np.array_equal(result.poses[:, :2], expected.poses[:, :2])
    np.testing.assert_allclose(result.poses[:, 2], expected.poses[:, 2], rtol=0, atol=1e-12)


def test_n144_poses_farther_apart_than_the_gyro_buffer_are_counted_unchecked(drive):
    """The gyro keeps a few seconds: a reference every 7 s is learned from unjudged, counted."""
    dense = _learn(drive, _reference(drive), 'fuse')
    full = _reference(drive, 20.0, 80.0)
    sparse_track = PoseTrack(full.t_ns[::70], full.x[::70], full.y[::70], full.yaw[::70])
    odometer = online_odometer(OdometryConfig.from_flat(
        {**FILE, 'imu.mode': 'fuse', 'online.max_gap': 20.0}))
    odometer.predict(drive.wheels, reference=sparse_track, imu=drive.imu)
    assert dense.counters['reference_gyro_unchecked'] <= 1   # the first interval at most
    counters = odometer.counters
    # every pose that reached the gyro's judgement (the others: refused as jumps or gaps first)
    assert counters['reference_gyro_unchecked'] >= 3
    assert counters['reference_gyro'] == 0


def test_n150_the_gyro_judges_the_reference_with_its_measured_heading_noise(drive):
    """A reference with 0.012 rad of heading noise (configured 0.005, within the 4x bound).

    The segments weigh it with the measured noise (refnoise.py); the gyro judged it with the
    configured one and refused 43 good poses (20 learning segments of 33). With the sigma in use
    it refuses only while the noise is not yet measured (the first 10 s).
    """
    t = np.arange(drive.start_ns, drive.end_ns, 100_000_000)
    truth = drive.truth_at(t)
    rng = np.random.default_rng(5)
    n = len(t)
    noisy = PoseTrack(t, truth.x + rng.normal(0, 0.01, n), truth.y + rng.normal(0, 0.01, n),
                      truth.yaw + rng.normal(0, 0.012, n))
    with_gyro = _learn(drive, noisy, 'fuse')
    without = _learn(drive, noisy, 'off')
    assert with_gyro.learner.reference_sigmas()[1] == pytest.approx(0.012, rel=0.25)
    assert with_gyro.counters['reference_gyro'] <= 10
    assert with_gyro.learner.gyro_refused_ns < drive.start_ns + int(12e9)
    assert with_gyro.counters['online_segments'] >= 0.9 * without.counters['online_segments']


# the noise a calibration fits on the simulator (the file's defaults are far wider)
NOISE_FITTED = {'var_x_per_m': 1.2e-4, 'var_y_per_m': 0.0, 'var_yaw_per_m': 0.0,
                'var_yaw_per_rad': 2.2e-4, 'var_x_const': 1.3e-5}


def test_n153_fused_heading_covariance_carries_the_residual_gyro_bias():
    # a gyro biased by imu.bias_sigma (one prior sigma, as a calibrated gyro may be), fused, with
    # online learning on: the bias is one error over the whole drive (heading error beta * T),
    # so the published heading variance must grow as bias_sigma^2 T^2 for the heading's NEES to
    # stay near 1 (summed as independent per-interval errors it was about 8).
    sim = simulate(SimConfig(duration_s=120.0, seed=7))
    noise = {f'models.edd_asymmetric.noise.{k}': v for k, v in NOISE_FITTED.items()}
    config = OdometryConfig.from_flat({**FILE, **noise, 'imu.mode': 'fuse'})
    bias = config.imu.bias_sigma
    imu = dataclasses.replace(sim.imu, yaw_rate=sim.imu.yaw_rate + bias)
    result = online_odometer(config).predict(sim.wheels, reference=_reference(sim), imu=imu)
    t = (sim.wheels.t_ns - sim.start_ns) * 1e-9
    pick = np.nonzero(t >= 20.0)[0][::20]
    err = sim.truth.poses[pick, 2] - result.poses[pick, 2]
    err = (err + np.pi) % (2 * np.pi) - np.pi
    var = result.pose_covariances[pick, 5, 5]
    assert abs(err[-1]) > 0.04   # the bias left its mark: the heading is off by beta * T
    assert np.mean(err ** 2 / var) < 3.0
