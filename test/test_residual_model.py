"""The data-driven residual model: bounded, clamped, streaming == batch, fitted and found."""

from dataclasses import replace

from lab.studies.effects import GEOMETRY, sim_drives, SIM_INTERVAL
from lab.studies.unnamed_effects import draw_effects
import numpy as np
import pytest
from skidkin_ros.core.calibration.diagnosis import diagnose, DiagnosisOptions
from skidkin_ros.core.calibration.diagnosis.regression import blr, fit_residual_model
from skidkin_ros.core.calibration.diagnosis.residuals import pose_samples
from skidkin_ros.core.calibration.fitting import fit_model
from skidkin_ros.core.calibration.segments import cut_segments
from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.core.kinematics import residual
from skidkin_ros.core.kinematics.augmented import AugmentedModel, MIN_RATE_STEP_S
from skidkin_ros.core.kinematics.extensions import get_extension
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.config import OdometryConfig, write_params_file
from skidkin_ros.core.odometry.odometer import Odometer, predict_wheels
from skidkin_ros.core.odometry.wheels import MIN_JUMP_INTERVAL_S
from skidkin_ros.sim.simulate import SimConfig, simulate

GEOM = Geometry(0.1651, 0.555)
BASE = get_model('edd_symmetric').bind({'alpha': 0.9, 'b_hat': 0.8}, GEOM)
RANGES = {'v_lo': -1.0, 'v_hi': 1.2, 'w_lo': -2.0, 'w_hi': 2.0, 'dv_lo': -3.0, 'dv_hi': 3.0,
          'dw_lo': -8.0, 'dw_hi': 8.0}


def _values(rng, scale=0.05):
    values = {name: float(rng.normal(0.0, scale)) for name in residual.coefficient_names()}
    values.update(RANGES)
    return values


def _model(values, name='residual_model'):
    return AugmentedModel('edd_symmetric', [name]).bind(BASE, {name: values})


def test_the_rate_floor_is_the_wheel_jump_rule():
    assert MIN_RATE_STEP_S == MIN_JUMP_INTERVAL_S == 0.01


@pytest.mark.parametrize('name, values', [
    ('sparse_correction', {'vx_dv': 10.0, 'wz_dw': -10.0, 'vy_dv': 10.0}),
    ('residual_model', {**dict.fromkeys(residual.coefficient_names(), 10.0), **RANGES}),
])
def test_c150_rate_terms_floor_dt_and_the_twist_is_bounded(name, values):
    """Stamps 1 us apart with coefficients inside their bounds: no absurd twist (C150).

    Before: the rate divided by 1 us and sparse_correction published 2.7e7 m/s.
    """
    model = _model(values, name)
    t_ns = np.concatenate([np.arange(20) * 50_000_000, [950_001_000, 950_002_000]])
    wl = np.concatenate([np.full(20, 5.0), [9.0, 4.5]])
    wr = np.concatenate([np.full(20, 5.0), [1.0, 5.5]])
    wheels = WheelSamples(t_ns.astype(np.int64), wl, wr)
    for interval in ('ending', 'starting', 'midpoint'):
        streamed = predict_wheels(wheels, model, interval=interval)
        assert np.all(np.isfinite(streamed.twists))
        # each change at most the motion's own size (|v| + 2 m |w|, |w| + |v| / 2 m)
        base = BASE.twist(wl, wr)
        bound = np.abs(base[:, 0]) + 2.0 * np.abs(base[:, 2])
        assert np.abs(streamed.twists[:, :2]).max() <= 2.0 * bound.max() + 1e-9
        assert np.abs(streamed.twists).max() < 20.0
    # batch form: the rate over 1 us counts as over 10 ms, as the streaming form has it
    dt = np.zeros((1, t_ns.size))
    dt[0, :-1] = np.diff(t_ns) * 1e-9
    held, _ = model.intervals(t_ns[None], wl[None], wr[None], dt, np.zeros((1, t_ns.size), bool))
    assert np.abs(held).max() < 20.0


def test_scalar_and_batch_forms_agree_bit_for_bit_inside_and_outside_the_range():
    rng = np.random.default_rng(3)
    values = _values(rng)
    ext = get_extension('residual_model')
    k = ext.vector(values)
    # inputs far outside the fitted range too (clamped)
    wl = rng.normal(0.0, 20.0, 400)
    wr = rng.normal(0.0, 20.0, 400)
    rate = rng.normal(0.0, 30.0, (400, 3))
    rate[::7] = 0.0
    base = BASE.twist(wl, wr)
    batch = ext.apply(k, base, wl, wr, np.zeros(400), rate)
    scalar = ext.scalar_apply()
    kk = tuple(k.tolist())
    for i in range(400):
        got = scalar(kk, *base[i].tolist(), wl[i], wr[i], 0.0, tuple(rate[i].tolist()))
        assert got == tuple(batch[i].tolist())
    assert np.all(np.isfinite(batch))


def test_a_sparse_file_takes_only_its_terms_and_equals_the_batch_form_bit_for_bit():
    """A level-3 file, v_y left out: the per-sample form evaluates only the terms in use.

    The sums are the batch form's (the same products in the same order, a term left out adds
    0.0), and the covariance's sensitivity of the coefficients carried is the full one's rows.
    """
    from skidkin_ros.core.kinematics.extensions import residual_jacobian
    rng = np.random.default_rng(5)
    low = set(residual.term_names(3))
    values = {name: (float(rng.normal(0.0, 0.05)) if name.split('_', 1)[1] in low
                     and not name.startswith('vy_') else 0.0)
              for name in residual.coefficient_names()}
    values.update(RANGES)
    ext = get_extension('residual_model')
    k = ext.vector(values)
    terms, outputs = residual.correction_plan(k)
    assert 0 < len(terms) == len(low) < len(residual.TERMS) and outputs[1] == ()
    wl, wr = rng.normal(0.0, 20.0, 300), rng.normal(0.0, 20.0, 300)
    rate = rng.normal(0.0, 30.0, (300, 3))
    base = BASE.twist(wl, wr)
    batch = ext.apply(k, base, wl, wr, np.zeros(300), rate)
    scalar = ext.scalar_apply()
    kk = tuple(k.tolist())
    index = [i for i, name in enumerate(residual.coefficient_names()) if values[name] != 0.0]
    for i in range(300):
        assert scalar(kk, *base[i].tolist(), wl[i], wr[i], 0.0,
                      tuple(rate[i].tolist())) == tuple(batch[i].tolist())
        full = residual_jacobian(kk, base[i].tolist(), rate[i].tolist())
        assert residual_jacobian(kk, base[i].tolist(), rate[i].tolist(), index) == [
            full[j] for j in index]


def test_outside_the_fitted_range_the_correction_holds_its_edge_value():
    values = {'vx_v_abs_v': -0.2, 'vx_v3': 0.1, **RANGES}
    model = _model(values)
    edge = BASE.twist(1.2 / (0.9 * GEOM.wheel_radius), 1.2 / (0.9 * GEOM.wheel_radius))
    twist_edge = model.memoryless(*(np.array([1.2 / (0.9 * GEOM.wheel_radius)]),) * 2, 0.0)[0]
    far = 10.0 / (0.9 * GEOM.wheel_radius)
    twist_far = model.memoryless(np.array([far]), np.array([far]), 0.0)[0]
    # the correction at 10 m/s equals the one at the range's edge (1.2 m/s)
    assert twist_far[0] - 10.0 == pytest.approx(twist_edge[0] - edge[0], abs=1e-12)
    # defaults are neutral: the base model exactly
    neutral = _model({})
    base = BASE.twist(np.array([3.0, -2.0]), np.array([1.0, 4.0]))
    np.testing.assert_array_equal(neutral.memoryless(np.array([3.0, -2.0]),
                                                     np.array([1.0, 4.0]), 0.0), base)


def test_blr_recovers_a_linear_function_and_its_uncertainty_shrinks_with_data():
    rng = np.random.default_rng(1)
    widths = []
    for n in (200, 3200):
        phi = rng.normal(size=(n, 4))
        y = phi @ np.array([0.5, 0.0, -0.2, 0.1]) + rng.normal(0.0, 0.1, n)
        fit = blr(phi, y)
        np.testing.assert_allclose(fit.mean, [0.5, 0.0, -0.2, 0.1], atol=0.03)
        assert 1.0 / fit.beta == pytest.approx(0.01, rel=0.2)
        widths.append(np.sqrt(fit.cov[0, 0]))
    assert widths[1] < widths[0] / 3.0


def _diagnosed(effects, seeds_train=(1, 2), seeds_eval=(3,), duration_s=90.0):
    train = sim_drives(effects, list(seeds_train), duration_s)
    evaluate = sim_drives(effects, list(seeds_eval), duration_s)
    options = DiagnosisOptions(interval=SIM_INTERVAL)
    base = fit_model('edd_symmetric', GEOMETRY, cut_segments(train, options.train_segments()))
    return diagnose(train, evaluate, GEOMETRY, {'edd_symmetric': base.values}, 'edd_symmetric',
                    options)


def test_an_unnamed_smooth_effect_is_corrected_and_explained():
    """A traction asymmetry between left and right turns, which no extension names."""
    effects = draw_effects(np.random.default_rng(11), count=1, families=('turn_asymmetry',),
                           strength=(0.25, 0.25))
    result = _diagnosed(effects)
    assert 'residual_model' in result.extensions
    first, last = result.steps[1], result.steps[-1]
    assert last.stats_t.median < 0.7 * first.stats_t.median
    deps = result.residual_dependence()
    assert deps and deps[0].component == 'omega' and deps[0].shares[0][0] == 'w'
    text = '\n'.join(result.summary_lines())
    assert 'follows w' in text and 'clamped' in text
    params = result.to_parameters({'wheel_radius': 0.1651, 'track_width': 0.555})
    cov = np.asarray(params['augmented.residual_model.covariance'])
    assert cov.size == len(residual.coefficient_names()) ** 2 and cov.max() > 0.0


def test_the_residual_fit_keeps_level_zero_on_pure_noise():
    train = sim_drives((), [1, 2], 90.0)
    options = DiagnosisOptions(interval=SIM_INTERVAL)
    base = fit_model('edd_symmetric', GEOMETRY, cut_segments(train, options.train_segments()))
    bound = get_model('edd_symmetric').bind(base.values, GEOMETRY)
    samples = pose_samples(train, bound, options)
    fit = fit_residual_model(train, samples, bound, options)
    # no systematic effect: at most a small correction on one component
    assert sum(level > 0 for level in fit.levels) <= 1
    assert fit.inflation > 1.0


def _calibrated_file(tmp_path, values, covariance):
    flat = {'wheel_radius': 0.1651, 'track_width': 0.555, 'robot': 'sim_husky',
            'model': 'augmented', 'augmented.base': 'edd_symmetric',
            'augmented.extensions': 'residual_model', 'interval': 'ending',
            'models.edd_symmetric.alpha': 0.9, 'models.edd_symmetric.b_hat': 0.85,
            'models.edd_symmetric.noise.calibrated': True,
            'models.edd_symmetric.noise.var_x_per_m': 4e-4,
            'models.edd_symmetric.noise.var_y_per_m': 1e-4,
            'models.edd_symmetric.noise.var_yaw_per_m': 2e-5,
            'models.edd_symmetric.noise.var_yaw_per_rad': 5e-4,
            'augmented.residual_model.covariance': covariance}
    flat.update({f'augmented.residual_model.{k}': v for k, v in values.items()})
    return write_params_file(tmp_path / 'residual.yaml', flat, {'source': 'test'})


def _covariance(terms, variance):
    size = len(residual.coefficient_names())
    cov = np.zeros((size, size))
    for name in terms:
        i = residual.coefficient_names().index(name)
        cov[i, i] = variance
    return cov.ravel().tolist()


def test_the_coefficient_covariance_widens_the_published_covariance(tmp_path):
    wheels = simulate(SimConfig(duration_s=10.0, seed=4)).wheels
    values = {'vx_v_abs_v': -0.1, 'wz_w': 0.05, **RANGES}
    path = _calibrated_file(tmp_path, values, _covariance(['vx_v_abs_v', 'wz_w'], 1e-2))
    config = OdometryConfig.from_file(path)
    assert config.active_parameter_uncertainty is not None
    with_cov = Odometer.from_config(config).predict(wheels)
    without = Odometer.from_config(OdometryConfig.from_file(
        path, overrides={'use_parameter_covariance': False})).predict(wheels)
    assert np.array_equal(with_cov.poses, without.poses)
    ratio = with_cov.pose_covariances[-1, 0, 0] / without.pose_covariances[-1, 0, 0]
    assert ratio > 1.2


@pytest.mark.ros
def test_node_runs_the_residual_model_bit_for_bit_with_its_covariance(tmp_path):
    from node_harness import assert_replay_matches
    from skidkin_ros.node.replay import replay_through_node
    wheels = simulate(SimConfig(duration_s=8.0, seed=8)).wheels
    rng = np.random.default_rng(5)
    values = _values(rng, 0.02)
    terms = ['vx_v_abs_v', 'vx_dv_up', 'wz_w_abs_v', 'vy_v_w']
    path = _calibrated_file(tmp_path, values, _covariance(terms, 4e-4))
    expected = Odometer.from_config(OdometryConfig.from_file(path)).predict(wheels)
    result = replay_through_node(wheels, params_file=path)
    assert_replay_matches(result, expected)   # twists bit for bit, poses to 1e-12
    np.testing.assert_array_equal(result.pose_cov, expected.pose_covariances)
    # the correction matters: the base model alone goes elsewhere
    base = predict_wheels(wheels, BASE, interval='ending')
    assert np.abs(base.twists[:, 0] - expected.twists[:, 0]).max() > 1e-3


def test_the_diagnosis_questions_the_base_model():
    """An asymmetric robot calibrated as edd_symmetric: the diagnosis replaces the base model."""
    from lab.studies.effects import icp_like
    made = []
    for seed in (21, 22, 23):
        sim = simulate(SimConfig(duration_s=90.0, seed=seed, internal_rate_hz=200.0))
        made.append(icp_like(sim.drive(f'asym{seed}'), np.random.default_rng(seed)))
    options = DiagnosisOptions(interval=SIM_INTERVAL)
    base = fit_model('edd_symmetric', GEOM, cut_segments(made[:2], options.train_segments()))
    result = diagnose(made[:2], made[2:], GEOM, {'edd_symmetric': base.values},
                      'edd_symmetric', options)
    assert result.given_base == 'edd_symmetric'
    text = '\n'.join(result.summary_lines())
    questioned = [line for line in result.provenance['base_models_questioned']
                  if line.startswith('edd_asymmetric: held-out gain ')]
    # the right base passes its own test by far
    assert questioned and float(questioned[0].split()[3].rstrip(',')) > 0.5
    if result.base_model == 'edd_symmetric':
        # kept only by the documented rule: the given model with its extensions ends lower on
        # held-out segments by more than the margin (the residual model standing in for the
        # asymmetry), and then its final model is no worse on the evaluation drive than the
        # right base's
        assert 'explains as much or more' in text
        right = diagnose(made[:2], made[2:], GEOM, {'edd_asymmetric': {}}, 'edd_asymmetric',
                         replace(options, question_base=False))
        assert result.steps[-1].stats_t.median <= right.steps[-1].stats_t.median
        assert result.steps[-1].stats_theta.median <= right.steps[-1].stats_theta.median
    else:
        assert result.base_model in ('edd_asymmetric', 'full_linear')
        assert 'replaces edd_symmetric' in text
        assert result.steps[1].stats_t.median < 0.8 * result.steps[0].stats_t.median
    params = result.to_parameters({'wheel_radius': 0.1651, 'track_width': 0.555,
                                   'model': 'edd_symmetric'})
    assert params.get('augmented.base', params['model']) == result.base_model


@pytest.mark.heavy
def test_the_residual_model_helps_on_the_real_husky_without_a_heading_loss():
    """The Husky windows (DRIVE), even calib_step train, odd evaluate: no loss, a gain in eps_t.

    The base refit drops the outlier segments (C211): on every segment a few ground-truth
    glitches pulled b_hat from 1.170 to 1.197, and the heading stayed 4 % worse than the plain fit.
    """
    from pathlib import Path
    from skidkin_ros.adapters.table import read_table
    from skidkin_ros.core.calibration.holdout import split_holdout
    data = Path(__file__).resolve().parents[1] / 'data' / 'husky' / 'drive_husky_windows.csv'
    train, evaluate = split_holdout(read_table(data), every=2, key='calib_step')
    options = DiagnosisOptions(candidates=('residual_model',), interval='ending',
                               question_base=False)
    base = fit_model('edd_symmetric', GEOM, cut_segments(train, options.train_segments()))
    result = diagnose(train, evaluate, GEOM, {'edd_symmetric': base.values}, 'edd_symmetric',
                      options, jobs=2)
    given, refitted, last = result.steps[0], result.steps[1], result.steps[-1]
    assert result.extensions == ('residual_model',)
    # no loss against the calibrated model nor the refitted one, on either error (C211)
    assert last.stats_t.median < 0.9 * given.stats_t.median
    assert last.stats_t.median <= refitted.stats_t.median
    assert last.stats_theta.median <= given.stats_theta.median
    assert last.stats_theta.median <= refitted.stats_theta.median


def test_every_library_term_lies_in_unit_range_and_all_but_the_rates_vanish_at_rest():
    rng = np.random.default_rng(5)
    ranges = [RANGES[name] for name in residual.range_names()]
    twist = rng.normal(0.0, 3.0, (2000, 3))
    rate = rng.normal(0.0, 10.0, (2000, 3))
    phi = residual.features(ranges, twist, rate)
    assert np.all(np.isfinite(phi)) and np.abs(phi).max() <= 1.0 + 1e-12
    rest = residual.features(ranges, np.zeros((1, 3)), np.zeros((1, 3)))[0]
    assert not np.any(rest)
    # at rest with a rate, only the terms of the rates alone are non-zero
    moving_rate = residual.features(ranges, np.zeros((1, 3)), np.ones((1, 3)))[0]
    nonzero = {name for name, x in zip(residual.term_names(), moving_rate) if x != 0.0}
    assert nonzero <= {'dv', 'dw'}


def test_the_spline_level_fits_a_saturating_yaw_slip_the_polynomials_miss():
    """A yaw slip that sets in at a turn rate (w0 = 0.7 rad/s) and saturates: turn slip."""
    rng = np.random.default_rng(2)
    ranges = [RANGES[name] for name in residual.range_names()]
    twist = np.zeros((3000, 3))
    twist[:, 0] = rng.uniform(-1.0, 1.2, 3000)
    twist[:, 2] = rng.uniform(-2.0, 2.0, 3000)
    w = twist[:, 2]
    target = -0.4 * w * (1.0 - np.exp(-(w / 0.7) ** 2))
    phi = residual.features(ranges, twist, np.zeros((3000, 3)))

    def rms_error(level):
        cols = [j for j, (_, lvl, _, _) in enumerate(residual.TERMS) if lvl <= level]
        coef = np.linalg.lstsq(phi[:, cols], target, rcond=None)[0]
        return float(np.sqrt(np.mean((phi[:, cols] @ coef - target) ** 2)))

    polynomial, spline = rms_error(5), rms_error(6)
    assert spline < 0.3 * polynomial


def test_the_bump_level_fits_a_random_smooth_function_of_speed_and_turn_rate():
    """Gaussian bumps over (v, w), as the study's random smooth functions: v, w *= 1 + sum g.

    Every product of one-signal terms (levels 1-6) leaves a bias in the region of each bump;
    the tents of level 7 follow it.
    """
    rng = np.random.default_rng(5)
    ranges = [RANGES[name] for name in residual.range_names()]
    twist = np.zeros((4000, 3))
    twist[:, 0] = rng.uniform(-1.0, 1.2, 4000)
    twist[:, 2] = rng.uniform(-2.0, 2.0, 4000)
    v, w = twist[:, 0], twist[:, 2]
    gain = sum(a * np.exp(-0.5 * (((v - cv) / 0.35) ** 2 + ((w / 2.0 - cw) / 0.35) ** 2))
               for a, cv, cw in ((0.25, 0.5, 0.3), (-0.2, -0.4, -0.5), (0.15, 0.2, -0.6)))
    phi = residual.features(ranges, twist, np.zeros((4000, 3)))
    for target in (v * gain, w * gain):
        def rms_error(level):
            cols = [j for j, (_, lvl, _, _) in enumerate(residual.TERMS) if lvl <= level]
            coef = np.linalg.lstsq(phi[:, cols], target, rcond=None)[0]
            return float(np.sqrt(np.mean((phi[:, cols] @ coef - target) ** 2)))

        assert rms_error(7) < 0.5 * rms_error(6)


def test_the_turn_fraction_terms_fit_a_forward_loss_in_tight_turns():
    """A forward loss v k tanh((w L)^2 / (v^2 + c)): a function of the curvature."""
    rng = np.random.default_rng(4)
    ranges = [RANGES[name] for name in residual.range_names()]
    twist = np.zeros((3000, 3))
    twist[:, 0] = rng.uniform(-1.0, 1.2, 3000)
    twist[:, 2] = rng.uniform(-2.0, 2.0, 3000)
    v, w = twist[:, 0], twist[:, 2]
    target = -0.25 * v * np.tanh((0.25 * w) ** 2 / (v * v + 0.03))
    phi = residual.features(ranges, twist, np.zeros((3000, 3)))
    turn = [j for j, (name, _, _, _) in enumerate(residual.TERMS)
            if name.endswith(('_s2', '_abs_s'))]
    rest = [j for j, (_, lvl, _, _) in enumerate(residual.TERMS) if lvl <= 3]

    def rms_error(cols):
        coef = np.linalg.lstsq(phi[:, cols], target, rcond=None)[0]
        return float(np.sqrt(np.mean((phi[:, cols] @ coef - target) ** 2)))

    assert rms_error(rest + turn) < 0.6 * rms_error(rest)


def test_the_field_backlash_loses_its_play_at_each_reversal_and_nothing_else():
    """The study's backlash: the wheel follows its motor with a play; r x play is lost."""
    from lab.studies.unnamed_effects import SmoothEffect
    from skidkin_ros.sim.effects import EffectInput
    t_s = np.arange(0.0, 12.0, 0.001)
    v = np.where(t_s < 6.0, 0.5, -0.5)  # forward 3 m, then back 3 m: one reversal
    twist = np.stack([v, np.zeros_like(v), np.zeros_like(v)], axis=-1)
    play_rad = 0.3
    effect = SmoothEffect('field_backlash', play_rad, {}, 'backlash', ())
    out = effect.apply_twist(EffectInput(t_s, np.zeros_like(v), np.zeros_like(v), twist, None,
                                         12.0))
    dt = np.diff(t_s, prepend=t_s[0])
    forward = float(np.sum((out[:, 0] * dt)[t_s < 6.0]))
    backward = float(np.sum((out[:, 0] * dt)[t_s >= 6.0]))
    lost = GEOMETRY.wheel_radius * play_rad
    # half the play is taken up at the start (the wheel starts centred), all of it at the reversal
    assert forward == pytest.approx(3.0 - 0.5 * lost, abs=1e-3)
    assert backward == pytest.approx(-3.0 + lost, abs=1e-3)
    assert np.all(np.isfinite(out)) and not np.any(out[:, 2])


@pytest.mark.parametrize('layout', range(len(residual.LEGACY_LAYOUTS)))
def test_c230_a_file_of_an_earlier_library_loads_with_its_covariance(layout, tmp_path):
    """Its coefficients are read by name; its covariance is moved by name too.

    60 x 60 for the 20-term library, 120 x 120 for the 40-term one.
    """
    wheels = simulate(SimConfig(duration_s=10.0, seed=4)).wheels
    legacy = [f'{out}_{term}' for out, _ in residual.OUTPUTS
              for term in residual.LEGACY_LAYOUTS[layout]]
    rng = np.random.default_rng(3)
    root = rng.normal(size=(len(legacy), len(legacy))) * 1e-2
    old_cov = root @ root.T
    values = {'vx_v3': -0.05, 'wz_w': 0.05, **RANGES}
    old = OdometryConfig.from_file(_calibrated_file(tmp_path, values, old_cov.ravel().tolist()))
    names = residual.coefficient_names()
    new_cov = np.zeros((len(names), len(names)))
    index = [names.index(name) for name in legacy]
    new_cov[np.ix_(index, index)] = old_cov
    (tmp_path / 'residual.yaml').unlink()
    new = OdometryConfig.from_file(_calibrated_file(tmp_path, values, new_cov.ravel().tolist()))
    assert old.active_parameter_uncertainty is not None
    a, b = Odometer.from_config(old).predict(wheels), Odometer.from_config(new).predict(wheels)
    assert np.array_equal(a.poses, b.poses)
    assert np.array_equal(a.pose_covariances, b.pose_covariances)
    assert old['augmented.residual_model.covariance'] == new_cov.ravel().tolist()


@pytest.mark.parametrize('strength', [0.05, 0.0])
def test_a_slope_creep_nothing_explains_is_reported_as_unexplained(strength, tmp_path):
    """A lateral creep down a side slope follows the world heading, no wheel signal (C212).

    Nothing in the library can follow it: the diagnosis adds nothing and says which signal the
    residual left follows, on stdout and on the report's page; an effect-free drive says nothing.
    """
    from lab.studies.unnamed_effects import drives, SmoothEffect
    from skidkin_ros.report.diagnosis import write_diagnosis_report
    effects = [SmoothEffect('field_slope_creep', strength, {}, 'slope_creep', (0.7,))] \
        if strength else []
    train = drives(effects, [1050, 1051], 90.0, 'courtyard')
    evaluate = drives(effects, [1052, 1053], 90.0, 'courtyard')
    options = DiagnosisOptions(interval=SIM_INTERVAL)
    base = fit_model('edd_symmetric', GEOMETRY, cut_segments(train, options.train_segments()))
    result = diagnose(train, evaluate, GEOMETRY, {'edd_symmetric': base.values}, 'edd_symmetric',
                      options)
    text = '\n'.join(result.summary_lines())
    page = write_diagnosis_report(result, tmp_path / 'report').read_text()
    if strength:
        assert [lead.signal for lead in result.unexplained] == ['heading']
        assert result.unexplained[0].component == 'v_y'
        assert 'unexplained residual: signal heading' in text
        assert 'unexplained residual: signal heading' in page
    else:
        assert not result.unexplained and 'unexplained residual' not in text + page
