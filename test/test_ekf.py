"""The reference EKF: skidkin's prediction step, absolute pose corrections."""

import numpy as np
import pytest

from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.core.estimation.ekf import PlanarEkf, PoseFix
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.interval import held_wheels
from skidkin_ros.core.odometry.noise import NoiseModel
from skidkin_ros.core.odometry.odometer import predict_wheels
from skidkin_ros.core.odometry.propagation import predict
from skidkin_ros.errors import DataError, ParameterError

GEOMETRY = Geometry(0.1651, 0.555)
NOISE = NoiseModel(2e-4, 1e-4, 5e-4, 2e-3)
NS = 1_000_000_000


def _source(name='ideal_dd', values=None):
    return get_model(name).bind(values or {}, GEOMETRY)


def _straight(seconds=20.0, rate_hz=20.0, speed_rad_s=3.0):
    t_ns = (np.arange(int(seconds * rate_hz) + 1) * (NS / rate_hz)).astype(np.int64) + NS
    speeds = np.full(t_ns.size, speed_rad_s)
    return WheelSamples(t_ns, speeds, speeds.copy())


def test_without_fixes_the_ekf_is_the_integrator_and_the_prediction_api():
    rng = np.random.default_rng(3)
    n = 200
    t_ns = NS + np.cumsum(rng.integers(30_000_000, 70_000_000, n)).astype(np.int64)
    wheels = WheelSamples(t_ns, rng.uniform(-4, 6, n), rng.uniform(-4, 6, n))
    source = _source('edd_symmetric', {'alpha': 0.9, 'b_hat': 1.1})
    start = (1.0, -2.0, 0.4)
    ekf = PlanarEkf(source, NOISE, start, np.zeros((3, 3)))
    poses = []
    for t, wl, wr in zip(wheels.t_ns, wheels.omega_l, wheels.omega_r):
        ekf.predict(int(t), wl, wr)
        poses.append(ekf.pose.copy())
    # the filter holds each sample from its stamp: the starting convention
    stream = predict_wheels(wheels, source, start=start, interval='starting')
    np.testing.assert_allclose(np.array(poses), stream.poses, rtol=0, atol=1e-12)
    _, cov = predict(start, np.zeros((3, 3)), wheels.t_ns, wheels.omega_l, wheels.omega_r,
                     source, NOISE, interval='starting')
    np.testing.assert_allclose(ekf.cov, cov, rtol=1e-12, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(ekf.cov) > 0)
    # fed the held speeds of another convention, it follows the odometry under that one
    ending = PlanarEkf(source, NOISE, start, np.zeros((3, 3)))
    held = held_wheels(wheels, 'ending')
    for t, wl, wr in zip(held.t_ns, held.omega_l, held.omega_r):
        ending.predict(int(t), wl, wr)
    np.testing.assert_allclose(ending.pose, predict_wheels(wheels, source, start=start).poses[-1],
                               rtol=0, atol=1e-12)


def test_straight_line_with_fixes_converges_and_a_fix_shrinks_the_covariance():
    wheels = _straight()
    source = _source()
    truth = predict_wheels(wheels, source).poses   # exact motion: the model is the truth
    rng = np.random.default_rng(0)
    sigma = 0.05
    # start 1 m and 0.2 rad off, with a covariance that says so
    ekf = PlanarEkf(source, NOISE, (1.0, -1.0, 0.2), np.diag([1.0, 1.0, 0.05]))
    before_after = []
    errors = []
    for i, (t, wl, wr) in enumerate(zip(wheels.t_ns, wheels.omega_l, wheels.omega_r)):
        ekf.predict(int(t), wl, wr)
        if i % 20 == 0 and i > 0:   # 1 Hz
            prior = ekf.cov.copy()
            errors.append(np.hypot(*(truth[i, :2] - ekf.pose[:2])))
            fix = PoseFix(int(t), truth[i, 0] + rng.normal(0, sigma),
                          truth[i, 1] + rng.normal(0, sigma), None, np.eye(2) * sigma ** 2)
            innovation = ekf.correct(fix)
            before_after.append((prior, ekf.cov.copy(), innovation.nis))
    error = truth[-1] - ekf.pose
    assert np.hypot(error[0], error[1]) < 3 * sigma
    assert abs(error[2]) < 0.02            # yaw became observable through the motion
    for prior, posterior, _ in before_after:
        assert np.trace(posterior[:2, :2]) < np.trace(prior[:2, :2])
        assert np.all(np.linalg.eigvalsh(prior - posterior) > -1e-12)
    first_prior, first_post, first_nis = before_after[0]
    assert first_post[0, 0] < 0.01 < first_prior[0, 0]
    assert errors[0] > 1.0 and errors[1] < 0.3   # the first fix removes most of the offset
    # the start offset was honest (1 sigma): the innovations are chi2(2)-sized throughout
    assert first_nis < 9.0
    assert np.mean([nis for _, _, nis in before_after]) < 4.0


def test_yaw_fix_is_wrapped_and_corrects_the_heading():
    source = _source()
    ekf = PlanarEkf(source, NOISE, (0.0, 0.0, np.pi - 0.05), np.diag([0.01, 0.01, 0.01]))
    ekf.predict(NS, 0.0, 0.0)
    fix = PoseFix(NS, 0.0, 0.0, -np.pi + 0.05, np.diag([0.01, 0.01, 0.01]))
    innovation = ekf.correct(fix)
    assert innovation.residual[2] == pytest.approx(0.1, abs=1e-9)
    assert ekf.pose[2] == pytest.approx(np.pi, abs=1e-9)     # halfway, across the wrap
    assert ekf.cov[2, 2] == pytest.approx(0.005, rel=1e-9)


def test_a_fix_between_samples_predicts_with_the_held_speeds():
    source = _source()
    ekf = PlanarEkf(source, None, (0.0, 0.0, 0.0), np.eye(3) * 1e-6)
    ekf.predict(NS, 2.0, 2.0)
    speed = 2.0 * GEOMETRY.wheel_radius
    fix = PoseFix(NS + NS // 2, 0.5 * speed, 0.0, None, np.eye(2) * 1e-2)
    innovation = ekf.correct(fix)
    np.testing.assert_allclose(innovation.residual, [0.0, 0.0], atol=1e-12)
    assert ekf.t_ns == NS + NS // 2
    ekf.predict(2 * NS, 2.0, 2.0)
    assert ekf.pose[0] == pytest.approx(speed, rel=1e-12)


def test_bad_inputs_are_refused_with_a_reason():
    ekf = PlanarEkf(_source(), NOISE)
    ekf.predict(2 * NS, 1.0, 1.0)
    with pytest.raises(DataError, match='older'):
        ekf.predict(NS, 1.0, 1.0)
    with pytest.raises(DataError, match='non-finite'):
        ekf.predict(3 * NS, float('nan'), 1.0)
    with pytest.raises(ParameterError, match='2 x 2'):
        PoseFix(NS, 0.0, 0.0, None, np.eye(3))
    with pytest.raises(ParameterError, match='positive definite'):
        PoseFix(NS, 0.0, 0.0, 0.0, np.diag([1.0, 1.0, 0.0]))


def test_an_augmented_model_is_refused_with_a_way_out():
    from skidkin_ros.core.kinematics.augmented import AugmentedModel
    base = get_model('edd_symmetric').bind({'alpha': 0.9, 'b_hat': 1.5}, Geometry(0.3, 1.2))
    lagged = AugmentedModel('edd_symmetric', ('first_order_lag',)).bind(
        base, {'first_order_lag': {'tau_s': 0.3}})
    with pytest.raises(ParameterError, match='plain kinematic model.*predict'):
        PlanarEkf(lagged, None)
    PlanarEkf(base, None)  # its base model is taken
