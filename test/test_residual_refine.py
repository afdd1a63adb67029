"""The residual model's coefficients refined on whole segments' end poses."""

from lab.studies.effects import GEOMETRY, sim_drives, SIM_INTERVAL
from lab.studies.residual_refine import MIN_FOLD_SEGMENTS, refine_at, refine_coefficients
from lab.studies.unnamed_effects import draw_effects
import numpy as np
from skidkin_ros.core.calibration.diagnosis import DiagnosisOptions, ModelState
from skidkin_ros.core.calibration.diagnosis.regression import fit_residual_model
from skidkin_ros.core.calibration.diagnosis.residuals import pose_samples
from skidkin_ros.core.calibration.diagnosis.state import held_out_loss
from skidkin_ros.core.calibration.fitting import fit_model
from skidkin_ros.core.calibration.predictor import SegmentPredictor
from skidkin_ros.core.calibration.segments import cut_segments
from skidkin_ros.core.kinematics import residual
from skidkin_ros.core.kinematics.models import get_model

NAME = 'residual_model'


def _velocity_fit(families=('turn_slip',), strength=(0.35, 0.35), seeds=(1,), duration_s=60.0):
    """Simulate a known unnamed effect, fit the base, then the residual model on velocities."""
    effects = draw_effects(np.random.default_rng(5), count=1, families=families,
                           strength=strength)
    train = sim_drives(effects, list(seeds), duration_s)
    options = DiagnosisOptions(interval=SIM_INTERVAL)
    segments = cut_segments(train, options.train_segments())
    base = fit_model('edd_symmetric', GEOMETRY, segments)
    bound = get_model('edd_symmetric').bind(base.values, GEOMETRY)
    samples = pose_samples(train, bound, options)
    fit = fit_residual_model(train, samples, bound, options)
    state = ModelState((NAME,), dict(base.values), {NAME: dict(fit.values)}, (), (NAME,),
                       fit.covariance)
    predictor = SegmentPredictor(train, segments, options.max_dt_s, options.interval)
    return predictor, state, options


def _loss(predictor, state, options, keep=None):
    return float(held_out_loss(predictor, state.bind('edd_symmetric', GEOMETRY), options,
                               keep).sum())


def _used_block(state):
    names = residual.coefficient_names()
    cov = np.asarray(state.residual_covariance).reshape(len(names), len(names))
    used = [names.index(t) for t in state.terms(NAME)]
    return cov, used


def test_the_refinement_lowers_the_end_pose_error_and_keeps_the_covariance_definite():
    predictor, state, options = _velocity_fit()
    assert state.terms(NAME), 'the velocity fit found the turn slip'
    refined = refine_at(predictor, 'edd_symmetric', GEOMETRY, state, options, None, 1.0)
    before, after = _loss(predictor, state, options), _loss(predictor, refined, options)
    assert after < 0.995 * before   # the objective's data term, from a fit on velocities
    # only the coefficients in use move; the ranges, level and gains stay
    assert refined.terms(NAME) == state.terms(NAME)
    for key, value in state.ext_values[NAME].items():
        if key not in state.terms(NAME):
            assert refined.ext_values[NAME][key] == value
    cov, used = _used_block(refined)
    block = cov[np.ix_(used, used)]
    assert np.allclose(cov, cov.T)
    assert np.linalg.eigvalsh(block).min() > 0.0
    # the segments add information: the refined coefficients are no less certain on the whole
    prior, _ = _used_block(state)
    assert np.trace(block) < np.trace(prior[np.ix_(used, used)]) * 4.0
    unused = [j for j in range(cov.shape[0]) if j not in used]
    assert not cov[np.ix_(unused, unused)].any()


def test_a_strong_prior_keeps_the_velocity_fit_and_a_state_without_the_model_is_unchanged():
    predictor, state, options = _velocity_fit()
    held = refine_at(predictor, 'edd_symmetric', GEOMETRY, state, options, None, 1e9)
    start = np.array([state.ext_values[NAME][t] for t in state.terms(NAME)])
    moved = np.array([held.ext_values[NAME][t] for t in state.terms(NAME)])
    assert np.allclose(moved, start, atol=1e-6 * max(np.abs(start).max(), 1e-9))
    plain = ModelState((), dict(state.base_values), {})
    assert refine_coefficients(predictor, 'edd_symmetric', GEOMETRY, plain, options) is plain


def test_the_refinement_on_kept_segments_scores_only_those():
    predictor, state, options = _velocity_fit()
    keep = np.arange(0, len(predictor), 2)
    refined = refine_at(predictor, 'edd_symmetric', GEOMETRY, state, options, keep, 1.0)
    assert _loss(predictor, refined, options, keep) < _loss(predictor, state, options, keep)


def test_the_prior_weight_is_chosen_on_held_out_segments_or_the_velocity_fit_is_kept():
    predictor, state, options = _velocity_fit()
    chosen = refine_coefficients(predictor, 'edd_symmetric', GEOMETRY, state, options)
    # whatever it chose, it did not do worse on the segments than the velocity fit
    assert _loss(predictor, chosen, options) <= _loss(predictor, state, options)
    few = np.arange(2 * MIN_FOLD_SEGMENTS - 1)
    assert refine_coefficients(predictor, 'edd_symmetric', GEOMETRY, state, options,
                               few) is state


def _exact_drive(coefs):
    """Simulate a drive whose ground truth is the base model plus a known residual model."""
    from dataclasses import replace
    from lab.studies.effects import TRUE_PARAMS
    from skidkin_ros.core.drive import PoseTrack
    from skidkin_ros.core.kinematics.augmented import AugmentedModel
    from skidkin_ros.core.odometry.integrator import rollout_stream
    from skidkin_ros.sim.simulate import SimConfig, simulate
    drive = simulate(SimConfig(duration_s=60.0, seed=4, true_model='edd_symmetric',
                               true_params=TRUE_PARAMS)).drive('exact')
    base = get_model('edd_symmetric').bind(TRUE_PARAMS, GEOMETRY)
    truth_model = AugmentedModel('edd_symmetric', [NAME]).bind(base, {NAME: coefs})
    wheels = drive.wheels
    poses = rollout_stream(truth_model, wheels.t_ns, wheels.omega_l, wheels.omega_r,
                           interval=SIM_INTERVAL)
    held = np.arange(len(wheels)) // 2 * 2   # 10 Hz poses held onto the wheel grid
    return replace(drive, truth=PoseTrack(wheels.t_ns, *poses[held].T)), base


def test_the_window_terms_are_what_the_velocity_target_sees_of_a_known_correction():
    from skidkin_ros.core.calibration.diagnosis.window_features import window_terms
    ranges = {'v_lo': -1.5, 'v_hi': 1.5, 'w_lo': -2.0, 'w_hi': 2.0, 'dv_lo': -3.0,
              'dv_hi': 3.0, 'dw_lo': -8.0, 'dw_hi': 8.0}
    names = residual.term_names()
    chosen = {'v': 0.03, 'w_abs_w': -0.05}   # level-1/2 terms: a forward and a yaw loss
    coefs = dict(ranges)
    for term, value in chosen.items():
        assert term in names
        coefs[f'vx_{term}'] = value
        coefs[f'wz_{term}'] = value
    drive, base = _exact_drive(coefs)
    options = DiagnosisOptions(interval=SIM_INTERVAL)
    samples = pose_samples([drive], base, options)
    order = [ranges[name] for name in residual.range_names()]
    target, valid, moving, turning = window_terms([drive], samples, base, options, order,
                                                  options.smoothing_s)
    c = np.array([chosen.get(term, 0.0) for term in names])
    phi = residual.features(order, samples.base_twist, samples.base_rate)
    ok = valid & (np.abs(samples.base_twist[:, 0]) > 0.05)
    for component, terms in ((0, moving), (2, turning)):
        seen = np.sqrt(np.mean((target[ok, component] - terms[ok] @ c) ** 2))
        at_pose = np.sqrt(np.mean((target[ok, component] - phi[ok] @ c) ** 2))
        size = np.sqrt(np.mean(target[ok, component] ** 2))
        assert size > 5e-3   # the correction is there to be seen
        assert seen < 0.5 * at_pose and seen < 0.1 * size
