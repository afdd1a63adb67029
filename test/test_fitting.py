"""Model fitting: recovery of known parameters, C14, C15, C16, C20, C193."""

from _calib_synth import GEOMETRY, make_drive, TRUE_VALUES
import numpy as np
import pytest

from skidkin_ros.core.calibration import fitting
from skidkin_ros.core.calibration.fitting import (fit_model, fit_models, FitOptions,
                                                  segment_errors, segment_errors_jacobian)
from skidkin_ros.core.calibration.segments import cut_segments, SegmentOptions
from skidkin_ros.core.kinematics.models import get_model

SEGMENTS = SegmentOptions(horizon_m=2.0, horizon_rad=1.0)


def _segments(model, kind='rich', seed=1, duration_s=300.0, **noise):
    noise = noise or {'wheel_noise': 0.02, 'truth_noise_m': 0.005, 'truth_noise_rad': 0.002}
    drive = make_drive(model, kind=kind, duration_s=duration_s, rate_hz=20.0, truth_every=2,
                       seed=seed, **noise)
    return cut_segments([drive], SEGMENTS)


@pytest.mark.parametrize('model,rel_tol', [('edd_symmetric', 0.01), ('edd_asymmetric', 0.02),
                                           ('roc', 0.05), ('full_linear', 0.02)])
def test_each_model_recovers_its_true_parameters(model, rel_tol):
    segs = _segments(model)
    fit = fit_model(model, GEOMETRY, segs)
    assert fit.valid, fit.warnings
    for name, true in TRUE_VALUES[model].items():
        scale = max(abs(true), 0.05 if model != 'full_linear' else 0.01)
        assert abs(fit.values[name] - true) <= rel_tol * scale + 3 * fit.std_errors[name], name
        assert 0 < fit.std_errors[name] < 0.1 * scale


def test_all_five_models_in_one_call():
    segs = _segments('edd_asymmetric', duration_s=200.0)
    fits = fit_models(GEOMETRY, segs)
    assert list(fits) == ['ideal_dd', 'edd_symmetric', 'edd_asymmetric', 'roc', 'full_linear']
    assert fits['ideal_dd'].values == {} and fits['ideal_dd'].valid
    # the true model family fits far better than the ideal differential drive
    assert fits['edd_asymmetric'].cost < 0.01 * fits['ideal_dd'].cost


def test_no_turning_flags_turn_parameters():
    """C14: straight driving only: b_hat (and the ICR positions) cannot be observed."""
    segs = _segments('edd_symmetric', kind='straight', duration_s=200.0)
    fits = fit_models(GEOMETRY, segs, models=('edd_symmetric', 'edd_asymmetric'))
    sym = fits['edd_symmetric']
    assert not sym.valid and 'b_hat' in sym.unobservable and 'alpha' not in sym.unobservable
    assert any('not enough turning' in w and 'b_hat' in w for w in sym.warnings)
    assert {'x_v', 'y_l', 'y_r'} <= set(fits['edd_asymmetric'].unobservable)


def test_no_straight_driving_flags_slip_parameters():
    """C14: spins in place only: alpha and b_hat are confounded (only alpha / b_hat is seen)."""
    segs = _segments('edd_symmetric', kind='spin', duration_s=200.0)
    fit = fit_model('edd_symmetric', GEOMETRY, segs)
    assert not fit.valid and {'alpha', 'b_hat'} <= set(fit.unobservable)
    assert any('translation' in w for w in fit.warnings)


def test_outlier_segments_are_trimmed_and_counted():
    """C15: a few corrupted ground-truth ends (ICP failures) are dropped and reported."""
    segs = _segments('edd_symmetric', duration_s=300.0)
    rng = np.random.default_rng(5)
    bad = rng.choice(len(segs), size=6, replace=False)
    end = segs.end.copy()
    end[bad, :2] += rng.choice([-1.0, 1.0], size=(6, 2)) * 1.5
    end[bad, 2] += 0.8
    corrupted = type(segs)(**{**segs.__dict__, 'end': end})
    fit = fit_model('edd_symmetric', GEOMETRY, corrupted)
    assert fit.segments_trimmed >= 6
    assert set(bad) <= set(np.nonzero(fit.trimmed_mask)[0])
    assert fit.values['b_hat'] == pytest.approx(1.04, rel=0.01)
    plain = fit_model('edd_symmetric', GEOMETRY, corrupted, FitOptions(trim=False))
    assert plain.segments_trimmed == 0
    assert abs(plain.values['b_hat'] - 1.04) > abs(fit.values['b_hat'] - 1.04)
    robust = fit_model('edd_symmetric', GEOMETRY, corrupted,
                       FitOptions(trim=False, loss='soft_l1', f_scale=0.05))
    assert abs(robust.values['b_hat'] - 1.04) < abs(plain.values['b_hat'] - 1.04)


def test_parameter_on_a_bound_marks_the_fit_invalid():
    """C16: the robot moves 10 % further than r * omega: alpha wants > 1 and sits on its bound."""
    values = {'gamma_11': 0.0908, 'gamma_12': 0.0908, 'gamma_21': 0.0, 'gamma_22': 0.0,
              'gamma_31': -0.17, 'gamma_32': 0.17}
    drive = make_drive('full_linear', values, duration_s=200.0, rate_hz=20.0, truth_every=2,
                       seed=2)
    fit = fit_model('edd_symmetric', GEOMETRY, cut_segments([drive], SEGMENTS))
    assert fit.on_bound == ('alpha',) and not fit.valid
    assert any('sit on a bound' in w for w in fit.warnings)


def test_same_input_same_output():
    """C20: seeded starts: a rerun gives bit-identical parameters."""
    segs = _segments('edd_asymmetric', duration_s=150.0)
    first = fit_model('edd_asymmetric', GEOMETRY, segs, FitOptions(seed=3))
    second = fit_model('edd_asymmetric', GEOMETRY, segs, FitOptions(seed=3))
    assert first.values == second.values and first.std_errors == second.std_errors
    assert first.starts == 8


@pytest.mark.parametrize('model', ['edd_symmetric', 'edd_asymmetric', 'roc', 'full_linear'])
def test_c193_exact_jacobian_fits_land_where_finite_differences_do(model, monkeypatch):
    """C193: the plain fits' exact Jacobian equals central differences; same optimum as FD."""
    segs = _segments('edd_asymmetric', duration_s=200.0)
    spec = get_model(model)
    k = spec.vector({}, GEOMETRY) * 1.03
    exact = segment_errors_jacobian(spec, k, GEOMETRY, segs)
    central = np.zeros_like(exact)
    for j in range(k.size):
        step = 1e-6 * max(abs(k[j]), 1.0)
        plus, minus = k.copy(), k.copy()
        plus[j] += step
        minus[j] -= step
        central[:, :, j] = (segment_errors(spec, plus, GEOMETRY, segs)
                            - segment_errors(spec, minus, GEOMETRY, segs)) / (2 * step)
    assert np.abs(exact - central).max() <= 1e-6 * np.abs(central).max()
    fits = {}
    for flag in (False, True):
        monkeypatch.setattr(fitting, 'EXACT_JACOBIAN', flag)
        fits[flag] = fit_model(model, GEOMETRY, segs)
    by_fd, by_exact = fits[False], fits[True]
    for name, value in by_fd.values.items():
        # both stop within the solver's own tolerance (xtol 1e-8 of the value) of the optimum
        gap = abs(by_exact.values[name] - value)
        assert gap <= 1e-6 * by_fd.std_errors[name] + 2e-8 * abs(value), name
        assert by_exact.std_errors[name] == pytest.approx(by_fd.std_errors[name], rel=1e-6)
    assert by_exact.warnings == by_fd.warnings and by_exact.valid == by_fd.valid
    assert by_exact.segments_trimmed == by_fd.segments_trimmed
    assert by_exact.cost == pytest.approx(by_fd.cost, rel=1e-9)
