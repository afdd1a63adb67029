"""Noise-model calibration from segment residuals and its 95 % consistency."""

from _calib_synth import GEOMETRY, make_drive
import numpy as np
import pytest

from skidkin_ros.core.calibration.noise_fit import (calibrate_noise, consistency, coverage_scale,
                                                    fit_noise_model, segment_covariances,
                                                    segment_motion)
from skidkin_ros.core.calibration.segments import cut_segments, SegmentOptions
from skidkin_ros.core.odometry.noise import NoiseModel

VALUES = {'alpha': 0.9, 'b_hat': 1.04}
TRUE_NOISE = NoiseModel(4e-3, 1e-3, 2e-4, 5e-3)


def _segments():
    drive = make_drive('edd_symmetric', duration_s=900.0, rate_hz=10.0, truth_every=1, seed=8)
    return cut_segments([drive], SegmentOptions(horizon_m=2.0, horizon_rad=1.0))


def test_rates_recovered_and_errors_95_percent_inside():
    segs = _segments()
    motion = segment_motion('edd_symmetric', VALUES, GEOMETRY, segs)
    cov = segment_covariances(TRUE_NOISE, motion)
    rng = np.random.default_rng(1)
    errors = np.einsum('nij,nj->ni', np.linalg.cholesky(cov), rng.normal(size=(len(segs), 3)))
    fitted = fit_noise_model(errors, motion)
    assert fitted.var_x_per_m == pytest.approx(TRUE_NOISE.var_x_per_m, rel=0.3)
    assert fitted.var_y_per_m == pytest.approx(TRUE_NOISE.var_y_per_m, rel=0.3)
    # distance and rotation grow together on these segments: check the yaw variance they predict
    true_yaw = segment_covariances(TRUE_NOISE, motion)[:, 2, 2].sum()
    fitted_yaw = segment_covariances(fitted, motion)[:, 2, 2].sum()
    assert fitted_yaw == pytest.approx(true_yaw, rel=0.15)
    check = consistency(fitted, errors, motion)
    assert check.segments == len(segs)
    assert 0.92 <= check.inside_95_3dof <= 0.98
    assert 0.92 <= check.inside_95_position_2dof <= 0.98
    # a noise model 100x too small is flagged as inconsistent
    tiny = NoiseModel(*(v / 100 for v in TRUE_NOISE.as_dict().values()))
    assert consistency(tiny, errors, motion).inside_95_3dof < 0.5


def _draw(cov, rng, heavy):
    """Errors with covariance ``cov``: Gaussian, or heavy-tailed (1 in 5 three times wider).

    The heavy mixture has the same covariance; a Gaussian fitted to it covers about 90 % at 95 %,
    as on the Husky data.
    """
    white = rng.normal(size=(cov.shape[0], 3))
    if heavy:
        wide = rng.random((cov.shape[0], 1)) < 0.2
        white = np.where(wide, 3.0 * white, white) / np.sqrt(0.8 + 0.2 * 9.0)
    return np.einsum('nij,nj->ni', np.linalg.cholesky(cov), white)


def test_heavy_tails_are_covered_by_scaling_the_rates_and_gaussian_ones_are_left_alone():
    segs = _segments()
    motion = segment_motion('edd_symmetric', VALUES, GEOMETRY, segs)
    cov = segment_covariances(TRUE_NOISE, motion)
    rng = np.random.default_rng(4)
    gaussian = _draw(cov, rng, heavy=False)
    assert coverage_scale(fit_noise_model(gaussian, motion), gaussian, motion) < 1.15
    fit_on, check_on = _draw(cov, rng, heavy=True), _draw(cov, rng, heavy=True)
    fitted = fit_noise_model(fit_on, motion)
    assert consistency(fitted, check_on, motion).inside_95_3dof < 0.93  # over-confident
    scale = coverage_scale(fitted, fit_on, motion)
    assert scale > 1.1
    scaled = NoiseModel(*(v * scale for v in fitted.as_dict().values()))
    assert consistency(scaled, fit_on, motion).inside_95_3dof >= 0.95
    assert 0.93 <= consistency(scaled, check_on, motion).inside_95_3dof <= 0.98  # held out
    # a model that already covers is never shrunk
    wide = NoiseModel(*(v * 10 for v in TRUE_NOISE.as_dict().values()))
    assert coverage_scale(wide, fit_on, motion) == 1.0


def test_basis_rotates_into_the_segment_frame():
    segs = _segments()
    motion = segment_motion('edd_symmetric', VALUES, GEOMETRY, segs)
    # the longitudinal basis adds up to the distance travelled (its trace), whatever the turns
    np.testing.assert_allclose(np.trace(motion.basis_x[:, :2, :2], axis1=1, axis2=2),
                               motion.basis_yaw_m[:, 2, 2], rtol=1e-12)


def test_calibrate_noise_on_model_residuals():
    drive = make_drive('edd_symmetric', duration_s=300.0, rate_hz=20.0, truth_every=2, seed=2,
                       wheel_noise=0.3, truth_noise_m=0.01, truth_noise_rad=0.005)
    segs = cut_segments([drive], SegmentOptions(horizon_m=2.0))
    # several horizons, as the calibrator fits them: one cannot tell a constant from a variance
    # per second or per metre
    other = {h: cut_segments([drive], SegmentOptions(horizon_m=h)) for h in (0.5, 1.0, 4.0)}
    result = calibrate_noise('edd_symmetric', VALUES, GEOMETRY, segs, other)
    assert all(v >= 0 for v in result.noise.as_dict().values())
    # 1 cm of white noise on the truth at both segment ends: about 2e-4 m^2 of length-independent
    # x variance, which the constant term takes (the per-metre x rate of this drive is tiny)
    assert 1e-4 <= result.noise.var_x_const <= 1e-3
    # 0.3 rad/s of white noise on each wheel at 20 Hz: the forward speed's variance r^2 s^2 / 2
    # held for 0.05 s per sample adds r^2 s^2 / 2 * 0.05 m^2 per second of motion
    expected = GEOMETRY.wheel_radius ** 2 * 0.3 ** 2 / 2 * 0.05
    assert 0.5 * expected <= result.noise.var_x_per_s <= 2.0 * expected
    assert result.noise.var_x_per_m + result.noise.var_x_const > 0
    assert 0.8 <= result.consistency.inside_95_3dof <= 1.0
    assert result.coverage_scale >= 1.0
    ml = fit_noise_model(*_errors_and_motion(segs))
    assert result.noise.var_x_per_m == pytest.approx(ml.var_x_per_m * result.coverage_scale)


def _errors_and_motion(segs):
    from skidkin_ros.core.calibration.fitting import segment_errors
    from skidkin_ros.core.kinematics.models import get_model
    model = get_model('edd_symmetric')
    errors = segment_errors(model, model.vector(VALUES, GEOMETRY), GEOMETRY, segs)
    return errors, segment_motion('edd_symmetric', VALUES, GEOMETRY, segs)
