"""Noise at every horizon and the calibration's own uncertainty."""

from dataclasses import replace

from _calib_synth import GEOMETRY, make_drive
import numpy as np
import pytest

from skidkin_ros.core.calibration.noise_fit import (calibrate_noise, fit_noise_model,
                                                    parameter_sensitivity, segment_covariances,
                                                    segment_motion, SegmentMotion)
from skidkin_ros.core.calibration.pipeline import (calibrate, CalibrationOptions, noise_warnings,
                                                   result_to_parameters)
from skidkin_ros.core.calibration.segments import cut_segments, SegmentOptions
from skidkin_ros.core.estimation.nees import drive_nees
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.odometry.config import OdometryConfig, write_params_file
from skidkin_ros.core.odometry.noise import NoiseModel
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.core.odometry.propagation import predict
from skidkin_ros.core.odometry.uncertainty import ParameterUncertainty
from skidkin_ros.errors import ParameterError

VALUES = {'alpha': 0.9, 'b_hat': 1.04}
WITH_CONSTANT = NoiseModel(4e-4, 1e-4, 2e-5, 5e-4, 4e-4, 1e-4, 3e-4)
PARAM_COV = np.array([[4e-4, 1e-4], [1e-4, 9e-4]])


def _horizon_sets(noise, seed=1):
    drive = make_drive('edd_symmetric', duration_s=900.0, rate_hz=10.0, truth_every=1, seed=8)
    rng = np.random.default_rng(seed)
    errors, motions = [], []
    for horizon in (0.5, 1.0, 2.0, 4.0):
        segs = cut_segments([drive], SegmentOptions(horizon_m=horizon))
        motion = segment_motion('edd_symmetric', VALUES, GEOMETRY, segs)
        chol = np.linalg.cholesky(segment_covariances(noise, motion))
        errors.append(np.einsum('nij,nj->ni', chol, rng.normal(size=(len(segs), 3))))
        motions.append(motion)
    return np.concatenate(errors), SegmentMotion.concat(motions)


def test_the_length_independent_term_is_recovered_from_several_horizons():
    errors, motion = _horizon_sets(WITH_CONSTANT)
    fitted = fit_noise_model(errors, motion)
    for name in ('var_x_const', 'var_y_const', 'var_yaw_const', 'var_x_per_m'):
        assert getattr(fitted, name) == pytest.approx(getattr(WITH_CONSTANT, name), rel=0.35)
    # rates alone cannot: they inflate to cover the short segments
    rates_only = fit_noise_model(errors, motion, constant=False)
    assert not rates_only.has_constant
    assert rates_only.var_x_per_m > 1.8 * WITH_CONSTANT.var_x_per_m


def test_no_constant_is_invented_when_the_noise_has_none():
    rates = NoiseModel(4e-4, 1e-4, 2e-5, 5e-4)
    errors, motion = _horizon_sets(rates, seed=3)
    fitted = fit_noise_model(errors, motion)
    # every component's constant stays below a tenth of the one the same fit recovers when the
    # noise has it (WITH_CONSTANT: 4e-4, 1e-4, 3e-4; over seeds 1-8 at most 9 % of it) ...
    for name in ('var_x_const', 'var_y_const', 'var_yaw_const'):
        assert getattr(fitted, name) < 0.1 * getattr(WITH_CONSTANT, name), name
    # ... and the rates are not traded for it: they are recovered (var_yaw_per_m is not: on
    # these drives it is confounded with var_yaw_per_rad, which takes it)
    for name in ('var_x_per_m', 'var_y_per_m', 'var_yaw_per_rad'):
        assert getattr(fitted, name) == pytest.approx(getattr(rates, name), rel=0.15), name


def _segment_predictions(segs, bound, noise, params):
    """Yield (index, covariance predict gives) for five segments spread over the set."""
    for i in range(0, len(segs), max(len(segs) // 5, 1)):
        width = int((segs.dt_s[i] > 0).sum())
        t_ns = np.concatenate([[0], np.cumsum(np.round(segs.dt_s[i, :width] * 1e9))]).astype(
            np.int64)
        wl = np.concatenate([segs.omega_l[i, :width], [0.0]])
        wr = np.concatenate([segs.omega_r[i, :width], [0.0]])
        # segments hold each interval's speeds from its start: the 'starting' hold replays them
        _, cov = predict((0.0, 0.0, 0.0), np.zeros((3, 3)), t_ns, wl, wr, bound, noise,
                         parameters=params, interval='starting')
        yield i, cov


def test_segment_covariance_matches_the_node_propagation_with_constant_and_parameters():
    """noise_fit's segment covariance is what predict (the node's propagator) gives."""
    drive = make_drive('edd_symmetric', duration_s=60.0, rate_hz=20.0, truth_every=1, seed=2)
    segs = cut_segments([drive], SegmentOptions(horizon_m=2.0))
    motion = segment_motion('edd_symmetric', VALUES, GEOMETRY, segs, PARAM_COV)
    # every part of the noise model: rates, constant and the time in motion
    noise = replace(WITH_CONSTANT, var_x_per_s=3e-4, var_yaw_per_s=2e-4)
    expected = segment_covariances(noise, motion)
    model = get_model('edd_symmetric')
    bound = model.bind(VALUES, GEOMETRY)
    params = ParameterUncertainty.of_model(model, bound.k, GEOMETRY, PARAM_COV)
    for i, cov in _segment_predictions(segs, bound, noise, params):
        # the node carries d(pose)/dk step by step to second order in the step, the
        # calibrator differentiates the exact rollout: they agree to a fraction of a percent
        scale = np.sqrt(np.outer(np.diag(expected[i]), np.diag(expected[i])))
        assert np.abs(cov - expected[i]).max() <= 0.005 * scale.max()
        np.testing.assert_allclose(np.diag(cov), np.diag(expected[i]), rtol=0.005)


def test_parameter_covariance_propagation_matches_a_monte_carlo_over_parameter_draws():
    drive = make_drive('edd_symmetric', duration_s=40.0, rate_hz=20.0, seed=4)
    model = get_model('edd_symmetric')
    k = model.vector(VALUES, GEOMETRY)
    params = ParameterUncertainty.of_model(model, k, GEOMETRY, PARAM_COV)
    zero = NoiseModel(0.0, 0.0, 0.0, 0.0)
    w = drive.wheels
    mean, cov = predict((0.0, 0.0, 0.0), np.zeros((3, 3)), w.t_ns, w.omega_l, w.omega_r,
                        model.bind(VALUES, GEOMETRY), zero, parameters=params)
    rng = np.random.default_rng(0)
    ends = []
    for draw in rng.multivariate_normal(k, PARAM_COV, 400):
        bound = model.bind(model.mapping(draw), GEOMETRY)
        ends.append(predict((0.0, 0.0, 0.0), np.zeros((3, 3)), w.t_ns, w.omega_l, w.omega_r,
                            bound, None)[0])
    ends = np.array(ends)
    empirical = np.cov(ends.T)
    assert np.linalg.norm(mean[:2]) > 3.0  # a real drive, not a standstill
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), np.sqrt(np.diag(empirical)), rtol=0.12)
    # and the calibrator's segment sensitivity is the same derivative
    segs = cut_segments([drive], SegmentOptions(horizon_m=1e9, short_drive='whole'))
    sens = parameter_sensitivity('edd_symmetric', VALUES, GEOMETRY, segs)
    assert sens.shape == (1, 3, 2)


def _calibrated_file(tmp_path, **extra):
    flat = {'wheel_radius': GEOMETRY.wheel_radius, 'track_width': GEOMETRY.track_width,
            'model': 'edd_symmetric', 'models.edd_symmetric.alpha': 0.9,
            'models.edd_symmetric.b_hat': 1.04, 'models.edd_symmetric.noise.calibrated': True,
            'models.edd_symmetric.noise.var_x_per_m': 4e-4,
            'models.edd_symmetric.noise.var_y_per_m': 1e-4,
            'models.edd_symmetric.noise.var_yaw_per_m': 2e-5,
            'models.edd_symmetric.noise.var_yaw_per_rad': 5e-4}
    flat.update(extra)
    return write_params_file(tmp_path / 'params.yaml', flat, {'source': 'test'})


def test_a_file_without_the_new_fields_loads_as_before(tmp_path):
    path = _calibrated_file(tmp_path)
    text = path.read_text()
    assert 'var_x_const' not in text and 'parameter_covariance' not in text
    config = OdometryConfig.from_file(path)
    assert config.active_noise == NoiseModel(4e-4, 1e-4, 2e-5, 5e-4)
    assert not config.active_noise.has_constant
    assert config.active_parameter_uncertainty is None


def test_parameter_covariance_is_used_by_default_and_the_switch_turns_it_off(tmp_path):
    path = _calibrated_file(tmp_path, **{
        'models.edd_symmetric.parameter_covariance': PARAM_COV.ravel().tolist()})
    on = OdometryConfig.from_file(path)
    off = OdometryConfig.from_file(path, overrides={'use_parameter_covariance': False})
    assert on.active_parameter_uncertainty is not None
    assert off.active_parameter_uncertainty is None
    wheels = make_drive('edd_symmetric', duration_s=30.0, rate_hz=20.0, seed=5).wheels
    cov_on = Odometer.from_config(on).predict(wheels).pose_covariances[-1]
    cov_off = Odometer.from_config(off).predict(wheels).pose_covariances[-1]
    assert cov_on[0, 0] > 2.0 * cov_off[0, 0]
    np.testing.assert_array_equal(cov_on[2:5], cov_off[2:5])  # z, roll, pitch rows untouched


@pytest.mark.parametrize('values,needle', [
    ([1.0, 0.0, 0.0], '4 finite numbers'),
    ([1e-4, 2e-4, 0.0, 1e-4], 'not symmetric'),
    ([1e-4, 0.0, 0.0, -1e-4], 'positive semi-definite'),
])
def test_a_bad_parameter_covariance_names_the_parameter(tmp_path, values, needle):
    with pytest.raises(ParameterError, match=needle):
        OdometryConfig.from_flat({'models.edd_symmetric.parameter_covariance': values})


def test_calibration_writes_constant_and_parameter_covariance_and_checks_horizons(tmp_path):
    train = [make_drive('edd_symmetric', duration_s=300.0, rate_hz=20.0, truth_every=2,
                        wheel_noise=0.3, seed=s) for s in (1, 2)]
    held = [make_drive('edd_symmetric', duration_s=300.0, rate_hz=20.0, truth_every=2,
                       wheel_noise=0.3, seed=s) for s in (3, 4)]
    options = CalibrationOptions(models=('edd_symmetric',), n_starts=1)
    result = calibrate(train, held, GEOMETRY, options)
    fit = result.fits['edd_symmetric']
    assert fit.covariance.shape == (2, 2)
    np.testing.assert_allclose(np.sqrt(np.diag(fit.covariance)),
                               [fit.std_errors['alpha'], fit.std_errors['b_hat']])
    checks = result.noise['edd_symmetric'].consistency.horizons
    assert [c.horizon_m for c in checks] == [0.5, 1.0, 2.0, 4.0]
    path = write_params_file(tmp_path / 'calibrated.yaml', result_to_parameters(result),
                             {'source': 'test'})
    config = OdometryConfig.from_file(path)
    assert config.active_parameter_uncertainty is not None
    np.testing.assert_allclose(config.active_parameter_uncertainty.covariance, fit.covariance)
    assert 'var_yaw_const' in path.read_text()


def test_too_few_held_out_segments_are_said_to_be_too_few():
    drive = make_drive('edd_symmetric', duration_s=90.0, rate_hz=20.0, truth_every=2, seed=6)
    segs = cut_segments([drive], SegmentOptions(horizon_m=2.0))
    other = {4.0: cut_segments([drive], SegmentOptions(horizon_m=4.0))}
    fit = calibrate_noise('edd_symmetric', VALUES, GEOMETRY, segs, other)
    verdicts = {c.horizon_m: c.verdict for c in fit.consistency.horizons}
    assert verdicts[4.0] == 'too few segments to tell'


def test_over_confident_and_conservative_horizons_are_told_apart():
    """C42: ground-truth noise is a length-independent error; rates alone cannot cover it."""
    drive = make_drive('edd_symmetric', VALUES, duration_s=600.0, rate_hz=20.0, truth_every=2,
                       seed=6, truth_noise_m=0.01, truth_noise_rad=0.005)
    segs = cut_segments([drive], SegmentOptions(horizon_m=2.0))
    other = {0.5: cut_segments([drive], SegmentOptions(horizon_m=0.5))}
    rates_only = calibrate_noise('edd_symmetric', VALUES, GEOMETRY, segs, other, constant=False)
    checks = {c.horizon_m: c for c in rates_only.consistency.horizons}
    # measured: NEES 6.83 at 0.5 m (band [2.77, 3.24]), 1.76 at 2 m (band [2.56, 3.47])
    assert checks[0.5].verdict == 'over-confident' and checks[0.5].mean_nees > checks[0.5].band[1]
    assert checks[2.0].verdict == 'conservative' and checks[2.0].mean_nees < checks[2.0].band[0]
    # the calibrator warns about the over-confident horizon, naming it and its numbers, and not
    # about the conservative one (the coverage scale makes it conservative on purpose)
    (warning,) = noise_warnings(rates_only)
    assert warning.startswith('edd_symmetric: the covariance is over-confident on held-out '
                              '0.5 m segments (average NEES ')
    assert f'{checks[0.5].segments} segments' in warning


def test_whole_drive_nees_grows_without_the_parameter_term_and_is_flat_with_it():
    """Biased parameters: the per-metre noise alone is over-confident far from the start."""
    truth_values = {'alpha': 0.9, 'b_hat': 1.04}
    drives = [make_drive('edd_symmetric', truth_values, duration_s=120.0, rate_hz=20.0,
                         truth_every=1, seed=s) for s in range(10, 18)]
    model = get_model('edd_symmetric')
    rng = np.random.default_rng(2)
    sd = np.array([0.01, 0.02])
    noise = NoiseModel(1e-6, 1e-6, 1e-7, 1e-6)
    with_param, without = [], []
    for drive in drives:  # each drive: its own calibration error, drawn from PARAM
        k = model.vector(truth_values, GEOMETRY) + rng.normal(0.0, sd)
        source = model.bind(model.mapping(k), GEOMETRY)
        params = ParameterUncertainty.of_model(model, k, GEOMETRY, np.diag(sd ** 2))
        with_param.append(drive_nees([drive], source, noise, (1.0, 20.0), 15.0, params))
        without.append(drive_nees([drive], source, noise, (1.0, 20.0), 15.0, None))
    far_with = np.mean([w.nees[0, 1] for w in with_param])
    far_without = np.mean([w.nees[0, 1] for w in without])
    assert far_without > 10.0 * far_with
    assert 1.0 < far_with < 6.0


def test_predict_cli_writes_the_published_covariance_and_the_switch_changes_it(tmp_path):
    """On a bag, predict writes the covariance; --no-parameter-covariance drops the term."""
    from skidkin_ros.adapters.sim_writer import write_bag
    from skidkin_ros.cli.main import main
    from skidkin_ros.sim.lidar import LidarConfig
    from skidkin_ros.sim.simulate import SimConfig, simulate
    sim = simulate(SimConfig(duration_s=8.0, seed=3,
                             lidar=LidarConfig(azimuth_resolution_deg=12.0)))
    bag, _ = write_bag(sim, tmp_path / 'drive')
    path = _calibrated_file(tmp_path, **{
        'models.edd_symmetric.parameter_covariance': PARAM_COV.ravel().tolist()})
    outputs = {}
    for flag in ('', '--no-parameter-covariance'):
        out = tmp_path / f'pred{flag}.csv'
        argv = ['predict', str(bag), '--params', str(path), '--out', str(out)]
        assert main(argv + ([flag] if flag else [])) == 0
        outputs[flag] = np.genfromtxt(out, delimiter=',', names=True)
    on, off = outputs[''], outputs['--no-parameter-covariance']
    assert on['cov_xx'][-1] > 2.0 * off['cov_xx'][-1]
    np.testing.assert_array_equal(on['x'], off['x'])


def test_roc_parameter_covariance_is_carried_by_the_node_propagation():
    """The node's S Sigma_k S^T for ROC is the calibrator's (noise_fit.parameter_sensitivity).

    ROC is not linear in the wheel speeds: the node differentiates its twist at each step's.
    """
    values = {'alpha': 0.9, 'beta_1': 0.6, 'beta_2': 0.3}
    cov_k = np.diag([1e-4, 4e-4, 9e-4])
    drive = make_drive('roc', duration_s=40.0, rate_hz=20.0, truth_every=1, seed=3)
    segs = cut_segments([drive], SegmentOptions(horizon_m=2.0))
    expected = segment_motion('roc', values, GEOMETRY, segs, cov_k).fixed
    model = get_model('roc')
    bound = model.bind(values, GEOMETRY)
    params = ParameterUncertainty.of_model(model, bound.k, GEOMETRY, cov_k)
    assert params is not None and params.size == 3
    zero = NoiseModel(0.0, 0.0, 0.0, 0.0)
    checked = 0
    for i, cov in _segment_predictions(segs, bound, zero, params):
        np.testing.assert_allclose(np.diag(cov), np.diag(expected[i]), rtol=0.01)
        assert np.diag(cov).max() > 1e-8  # not the zero of a sensitivity never carried
        checked += 1
    assert checked >= 3


def _lapack_inverse(cov):
    return np.linalg.inv(cov), np.linalg.det(cov)


def test_c194_the_closed_form_inverse_fits_what_lapack_fits(monkeypatch):
    """C194: the likelihood's 3x3 inverse by cofactors is LAPACK's to rounding; same fit."""
    from skidkin_ros.core.calibration import noise_fit
    errors, motion = _horizon_sets(WITH_CONSTANT, seed=2)
    cov = segment_covariances(WITH_CONSTANT, motion)
    # near-singular too: a covariance with almost no lateral variance
    thin = cov.copy()
    thin[:, 1, 1] = thin[:, 1, 0] * thin[:, 0, 1] / thin[:, 0, 0] + 1e-12
    for batch in (cov, thin):
        inv, det = noise_fit._inverse_3x3(batch)
        ref_inv, ref_det = _lapack_inverse(batch)
        assert np.allclose(det, ref_det, rtol=1e-9, atol=0.0)
        scale = np.abs(ref_inv).max(axis=(1, 2))[:, None, None]
        assert np.all(np.abs(inv - ref_inv) <= 1e-6 * scale)
    fitted = fit_noise_model(errors, motion)
    monkeypatch.setattr(noise_fit, '_inverse_3x3', _lapack_inverse)
    reference = fit_noise_model(errors, motion)
    # values the truth has to 1e-4 of themselves; those it lacks (per second here, nearly flat
    # in the likelihood) to 5e-5 of its smallest value (2e-5)
    for name, value in reference.as_dict().items():
        assert getattr(fitted, name) == pytest.approx(value, rel=1e-4, abs=1e-9), name
