"""Iterated weighting, the likelihood rule, roc's fit range, evaluate."""

from dataclasses import replace

import numpy as np
import pytest
from skidkin_ros.adapters.sim_writer import write_truth_csv
from skidkin_ros.cli.main import main
from skidkin_ros.core.calibration.engine import ParameterLayout
from skidkin_ros.core.calibration.evaluation import window_end_errors
from skidkin_ros.core.calibration.fitting import (fit_model, FitOptions, parameter_scales,
                                                  segment_errors, solve_model)
from skidkin_ros.core.calibration.segments import cut_segments, HorizonOptions, SegmentOptions
from skidkin_ros.core.calibration.selection import (choose_by_likelihood,
                                                    clustered_standard_error)
from skidkin_ros.core.calibration.weighting import (fit_model_iterated, noise_covariances,
                                                    whitening_matrices)
from skidkin_ros.core.kinematics.models import get_model, ROC_MAX_GAIN, RocModel
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.config import OdometryConfig, read_params_file
from skidkin_ros.sim.simulate import SimConfig, simulate

WARTHOG = Geometry(0.3, 1.2)
WARTHOG_TRUE = {'alpha_l': 0.92, 'alpha_r': 0.9, 'x_v': -0.08, 'y_l': 0.95, 'y_r': -1.0}


def warthog(seed, duration_s, true=None):
    """Simulate a Warthog-like robot (r 0.3 m, b 1.2 m, ICRs far outside the wheels)."""
    return simulate(SimConfig(
        duration_s=duration_s, seed=seed, wheel_radius=0.3, track_width=1.2,
        true_model='edd_asymmetric', true_params=dict(true or WARTHOG_TRUE),
        max_wheel_speed_rad_s=5.0, arena_radius_m=15.0, scene_half_size_m=32.0, motor_tau_s=0.2,
        internal_rate_hz=200.0))


def test_roc_fit_range_keeps_the_icr_distance_away_from_the_singularity_clamp():
    lo, hi = ParameterLayout.of_model('roc', WARTHOG).bounds()
    assert lo[1] == 0.0 and lo[2] == 0.0 and hi[1] == ROC_MAX_GAIN
    rng = np.random.default_rng(0)
    speeds = np.linspace(-6.0, 6.0, 41)
    left, right = (a.ravel() for a in np.meshgrid(speeds, speeds))
    b = WARTHOG.track_width
    for beta_1 in (lo[1], 1e-9, 0.6, 50.0, hi[1]):
        for beta_2 in (lo[2], 1e-12, 0.3, 1e6, *rng.uniform(0.0, 10.0, 3)):
            y0 = RocModel.icr_distance(np.array([0.9, beta_1, beta_2]), WARTHOG, left, right)
            assert np.all(y0 >= b / 2 - 1e-12)
            assert np.all(y0 <= b / 2 * (1 + beta_1) + 1e-9)
            assert np.all(y0 < 999.0 * b)  # never on the clamp [b/1000, 1000 b]


def test_a_roc_fit_on_beta_2_zero_is_a_valid_constrained_minimum_equal_to_edd_symmetric():
    # C31/C170: the truth's ICR gain grows along the path (beta_2 = -0.05, outside Wang et al.'s
    # range): the fit stops on beta_2 = 0, which is part of the model (a gain that does not
    # decay), so the fit is valid and is edd_symmetric with b_hat = b (1 + beta_1)
    sim = simulate(SimConfig(
        duration_s=150.0, seed=3, wheel_radius=0.3, track_width=1.2, true_model='roc',
        true_params={'alpha': 0.9, 'beta_1': 0.6, 'beta_2': -0.05}, max_wheel_speed_rad_s=5.0,
        arena_radius_m=15.0, scene_half_size_m=32.0, motor_tau_s=0.2, internal_rate_hz=200.0))
    segments = cut_segments([sim.drive('train')], HorizonOptions().train_segments())
    fit = fit_model('roc', WARTHOG, segments)
    assert fit.values['beta_2'] == pytest.approx(0.0, abs=1e-9)  # measured: 2e-25
    assert fit.valid and fit.on_bound == () and fit.at_constraint == ('beta_2',)
    assert not any('sit on a bound' in w for w in fit.warnings)
    sym = fit_model('edd_symmetric', WARTHOG, segments)
    assert sym.values['alpha'] == pytest.approx(fit.values['alpha'], rel=1e-4)
    assert sym.values['b_hat'] == pytest.approx(
        WARTHOG.track_width * (1.0 + fit.values['beta_1']), rel=1e-4)
    assert fit.cost == pytest.approx(sym.cost, rel=1e-6)
    # a constrained minimum: moving beta_2 into the model (> 0) only raises the cost
    model = get_model('roc')
    k = model.vector(fit.values, WARTHOG)
    base = (segment_errors(model, k, WARTHOG, segments) ** 2).sum()
    for step in (1e-3, 1e-2, 1e-1):
        moved = (segment_errors(model, k + np.array([0.0, 0.0, step]), WARTHOG,
                                segments) ** 2).sum()
        assert moved > base


def test_roc_with_beta_1_on_its_guard_is_still_invalid():
    # the upper end of beta_1 (1000) is a guard against the clamp, not part of the model
    spec = get_model('roc').params[1]
    assert spec.on_bound(ROC_MAX_GAIN) and not spec.at_constraint(ROC_MAX_GAIN)
    assert get_model('roc').params[2].at_constraint(0.0)
    assert not get_model('roc').params[2].on_bound(0.0)


def test_an_old_file_with_a_negative_beta_2_still_loads():
    config = OdometryConfig.from_flat({'model': 'roc', 'models.roc.alpha': 0.9,
                                       'models.roc.beta_1': 0.6, 'models.roc.beta_2': -0.046})
    assert config.model_values['roc']['beta_2'] == -0.046


def test_choose_by_likelihood_takes_fewer_parameters_within_two_standard_errors():
    rng = np.random.default_rng(1)
    clusters = np.repeat(np.arange(40), 5)
    common = rng.normal(0.0, 1.0, clusters.size)
    rich = common.copy()
    wiggle = rng.normal(0.0, 0.3, clusters.size)
    wiggle -= wiggle.mean()
    close = common + 0.02 + wiggle                                   # worse, within noise
    far = common + 0.5 + wiggle                                      # clearly worse
    params = {'rich': 6, 'close': 2, 'far': 1}
    best, table = choose_by_likelihood({'rich': rich, 'close': close, 'far': far}, clusters,
                                       params)
    assert best == 'close'
    assert table['rich'].delta == 0.0
    assert table['far'].delta > 2 * table['far'].standard_error
    best, _ = choose_by_likelihood({'rich': rich, 'far': far}, clusters, params)
    assert best == 'rich'
    # a non-finite NLL (a model that could not predict) never wins
    best, table = choose_by_likelihood({'rich': rich, 'far': np.full(rich.size, np.inf)},
                                       clusters, params)
    assert best == 'rich'


def test_clustered_standard_error_grows_when_segments_of_a_group_agree():
    clusters = np.repeat(np.arange(20), 10)
    independent = np.random.default_rng(2).normal(0.0, 1.0, clusters.size)
    grouped = np.repeat(np.random.default_rng(3).normal(0.0, 1.0, 20), 10)
    assert clustered_standard_error(grouped, clusters) > 2 * clustered_standard_error(
        independent, clusters)


@pytest.fixture(scope='module')
def skidding_drives():
    """Simulate a drive where identity weighting under-fits heading.

    The ICRs sit 0.3 m behind the axle: the lateral drift this gives cannot be followed by
    edd_symmetric, and with Sigma = identity its fit trades heading for position.
    """
    true = dict(WARTHOG_TRUE, x_v=-0.3)
    train = warthog(1, 300.0, true=true).drive('train')
    evaluate = [warthog(101, 150.0, true=true).drive('eval')]
    return train, evaluate


def _window_end(name, values, evaluate):
    windows = cut_segments(evaluate, SegmentOptions(horizon_s=2.0, short_drive='drop'))
    return window_end_errors(name, values, WARTHOG, windows)


def test_iterated_fit_holds_heading_at_window_ends_where_identity_under_fits(skidding_drives):
    train, evaluate = skidding_drives
    segments = cut_segments([train], HorizonOptions().train_segments())
    identity = fit_model('edd_symmetric', WARTHOG, segments)
    iterated = fit_model_iterated('edd_symmetric', WARTHOG, segments)
    assert iterated.weighting == 'iterated' and iterated.iterations >= 2
    assert iterated.valid
    end_identity = _window_end('edd_symmetric', identity.values, evaluate)
    end_iterated = _window_end('edd_symmetric', iterated.values, evaluate)
    assert end_iterated.yaw_rad < 0.85 * end_identity.yaw_rad  # measured: 0.68
    assert end_iterated.position_m < 1.05 * end_identity.position_m


def test_iterated_fit_recovers_the_true_parameters_at_least_as_well_as_identity():
    train = warthog(7, 240.0).drive('train')
    segments = cut_segments([train], HorizonOptions().train_segments())
    truth = np.array(list(WARTHOG_TRUE.values()))
    scale = np.array([1.0, 1.0, WARTHOG.track_width, WARTHOG.track_width,
                      WARTHOG.track_width])
    error = {}
    for label, fit in (('identity', fit_model), ('iterated', fit_model_iterated)):
        result = fit('edd_asymmetric', WARTHOG, segments)
        assert result.valid
        error[label] = np.abs(np.array(list(result.values.values())) - truth) / scale
    assert error['iterated'].max() < 0.01
    assert np.linalg.norm(error['iterated']) <= 1.25 * np.linalg.norm(error['identity'])


@pytest.fixture(scope='module')
def one_invalid_table(tmp_path_factory):
    """Write a Warthog-like drive whose left side wants alpha_l > 1 at the given radius.

    The table is calibrated with a wheel radius 5 % too small: edd_asymmetric's alpha_l wants
    1.05 and ends on its bound 1 (invalid), edd_symmetric's alpha about 0.95 (valid).
    """
    folder = tmp_path_factory.mktemp('warthog')
    true = {'alpha_l': 1.0, 'alpha_r': 0.8, 'x_v': -0.08, 'y_l': 0.95, 'y_r': -1.0}
    return write_truth_csv(warthog(3, 150.0, true), folder / 'warthog.csv')


def _calibrate(table, out, *extra):
    return main(['calibrate', str(table), '--wheel-radius', '0.285', '--track-width', '1.2',
                 '--models', 'edd_symmetric', 'edd_asymmetric', '--out', str(out), *extra])


def test_an_invalid_model_that_was_not_selected_is_a_warning_unless_strict(
        one_invalid_table, tmp_path, capsys):
    out = tmp_path / 'p.yaml'
    assert _calibrate(one_invalid_table, out) == 0
    text = capsys.readouterr()
    assert 'edd_asymmetric' in text.out and 'were not written' in text.out
    assert '--strict' in text.out
    flat = read_params_file(out)
    assert flat['model'] == 'edd_symmetric'
    assert not any(name.startswith('models.edd_asymmetric.') for name in flat)
    OdometryConfig.from_flat(flat)  # the node loads what was written
    strict = tmp_path / 'strict.yaml'
    assert _calibrate(one_invalid_table, strict, '--strict') == 4
    assert 'edd_asymmetric' in capsys.readouterr().err
    # the deprecated --accept-invalid still undoes --strict (scripts keep working) and says so
    assert _calibrate(one_invalid_table, tmp_path / 'accept.yaml', '--strict',
                      '--accept-invalid') == 0
    assert '--accept-invalid is deprecated (it undoes --strict' in capsys.readouterr().err
    assert _calibrate(one_invalid_table, tmp_path / 'plain.yaml', '--accept-invalid') == 0
    assert '--accept-invalid is deprecated (it does nothing' in capsys.readouterr().err


def test_evaluate_refuses_a_model_the_file_does_not_hold(one_invalid_table, tmp_path, capsys):
    out = tmp_path / 'p.yaml'
    assert _calibrate(one_invalid_table, out) == 0
    capsys.readouterr()
    assert main(['evaluate', str(one_invalid_table), '--params', str(out), '--models',
                 'edd_asymmetric']) == 2
    err = capsys.readouterr().err
    assert 'not in the file' in err and 'Traceback' not in err
    # C33: the error names the models the file does hold, to pick from
    held = err.split('(it holds ', 1)[1].split(')', 1)[0].split(', ')
    assert 'edd_symmetric' in held and 'edd_asymmetric' not in held
    assert main(['evaluate', str(one_invalid_table), '--params', str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert any('not in the file' in line and 'edd_asymmetric' in line for line in lines)
    scored = [line.split()[0] for line in lines if line.split()]
    assert 'edd_symmetric' in scored and 'edd_asymmetric' not in scored


def test_fixed_weighting_is_still_available_and_the_iterated_fit_is_the_gls_optimum(
        skidding_drives):
    train, _ = skidding_drives
    segments = cut_segments([train], HorizonOptions().train_segments())
    options = FitOptions(trim=False)  # the same segments for both: no trimming
    fixed = fit_model('edd_symmetric', WARTHOG, segments, options)
    iterated = fit_model_iterated('edd_symmetric', WARTHOG, segments, options)
    assert fixed.weighting == 'fixed' and iterated.weighting == 'iterated'
    model = get_model('edd_symmetric')
    assert model.param_names == tuple(iterated.values)
    assert replace(fixed, weighting='iterated').weighting == 'iterated'
    # The GLS optimum under the weights the iterated values give (the noise model fitted on
    # their residuals) is known by solving for it, from the fixed fit's values: the iterated fit
    # is that optimum (measured: 2e-5 of a typical magnitude away, the fixed fit 7.6e-3), and it
    # lowers the whitened cost the fixed fit leaves (measured: 430 -> 399).
    k_fixed = model.vector(fixed.values, WARTHOG)
    k_iterated = model.vector(iterated.values, WARTHOG)
    errors = segment_errors(model, k_iterated, WARTHOG, segments)
    weight = whitening_matrices(noise_covariances('edd_symmetric', iterated.values, WARTHOG,
                                                  segments, errors, max_fit_segments=300))
    optimum = solve_model(model, WARTHOG, segments, options, k_fixed, weight=weight).x
    typical = parameter_scales(model, WARTHOG)
    to_optimum = np.abs(k_iterated - optimum) / typical
    assert to_optimum.max() < 1e-3  # the iteration's tolerance
    assert (np.abs(k_fixed - optimum) / typical).max() > 20 * to_optimum.max()

    def cost(k):
        white = np.einsum('nij,nj->ni', weight, segment_errors(model, k, WARTHOG, segments))
        return float(np.sum(white ** 2))
    assert cost(k_iterated) < 0.95 * cost(k_fixed)


def test_one_evaluation_drive_falls_back_to_the_paper_rule_instead_of_failing():
    """A single evaluation drive has no second half for the likelihood: said, not a crash."""
    from _calib_synth import GEOMETRY, make_drive
    from skidkin_ros.core.calibration.pipeline import calibrate, CalibrationOptions

    train = [make_drive('edd_symmetric', duration_s=60.0, seed=s) for s in (1, 2)]
    evaluate = [make_drive('edd_symmetric', duration_s=60.0, seed=3)]
    result = calibrate(train, evaluate, GEOMETRY, CalibrationOptions(models=('edd_symmetric',)))
    assert result.selection_rule == 'paper'
    assert any('at least 2 drives' in w for w in result.warnings), result.warnings
