"""The diagnosis fits' cheaper rollouts compute what the exact ones do (C213, C214, C243, C244).

C213: the fits' trigonometry from the half-angle tangent equals numpy's sin and cos to a few
1e-16 (the node and ``skidkin predict`` keep numpy's, bit for bit); the segment windows' plan
from one search over every drive's stamps equals a search in each drive; the Jacobian that
skips directions whose tangent is 0 equals the one that sums them.
C214: the lag scan reads one rollout at every offset, and the differentiator keeps the entries
of its product that are used: both equal what they replace, bit for bit.
C243: the backlash's sample loop runs once for the same speeds, stamps and play (a fit's
Jacobian after its evaluation, every fold at the start value), and again when one changes.
C244: the residual model's level search takes each fold's rows once for all its levels, and
its correction reads the terms from one contiguous copy: both as before, bit for bit.
"""

import numpy as np
import pytest
from skidkin_ros.core.calibration.diagnosis import regression
from skidkin_ros.core.calibration.diagnosis.options import DiagnosisOptions
from skidkin_ros.core.calibration.diagnosis.regression import (_ranges, BLOCK_FOLDS, block_folds,
                                                               blr, fit_residual_model,
                                                               model_inputs)
from skidkin_ros.core.calibration.diagnosis.residuals import (_operator, body_velocities,
                                                              model_rollouts, pose_residuals,
                                                              pose_samples)
from skidkin_ros.core.calibration.diagnosis.window_features import window_terms
from skidkin_ros.core.calibration.predictor import SegmentPredictor
from skidkin_ros.core.calibration.segments import cut_segments, SegmentOptions
from skidkin_ros.core.drive import Drive, PoseTrack, WheelSamples
from skidkin_ros.core.kinematics import backlash, residual
from skidkin_ros.core.kinematics.augmented import AugmentedModel
from skidkin_ros.core.kinematics.backlash import PLAY_STATE, play_step
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.integrator import rollout
from skidkin_ros.core.odometry.se2 import _sinc_terms, body_increment, rollout_columns, sin_cos
from skidkin_ros.core.odometry.se2_tangent import window_tangents

GEOM = Geometry(0.1651, 0.555)
BASE = get_model('edd_symmetric').bind({'alpha': 0.9, 'b_hat': 0.8}, GEOM)


def _drive(seed, n, gap=False):
    """Random wheel speeds with a repeated stamp (and a gap); poses of another model."""
    rng = np.random.default_rng(seed)
    t_ns = 10**18 + seed * 10**12 + np.cumsum(rng.integers(30_000_000, 70_000_000, n))
    t_ns[n // 3] = t_ns[n // 3 - 1]
    if gap:
        t_ns[n // 2:] += 2_000_000_000
    t = (t_ns - t_ns[0]) * 1e-9
    wl = 5 * np.sin(0.3 * t + seed) + 2 * np.sin(1.3 * t)
    wr = 5 * np.sin(0.2 * t + 2 * seed) + 2 * np.cos(1.1 * t)
    truth = rollout(get_model('edd_asymmetric').bind(
        {'alpha_l': 0.85, 'alpha_r': 0.9, 'x_v': 0.05, 'y_l': 0.45, 'y_r': -0.4},
        GEOM).twist(wl[:-1], wr[:-1]), np.diff(t_ns) * 1e-9)
    keep = np.arange(0, n, 2)
    return Drive(f'd{seed}', WheelSamples(t_ns, wl, wr), PoseTrack(t_ns[keep], *truth[keep].T))


@pytest.fixture(scope='module')
def drives():
    # unequal lengths: the shorter drives are padded in the predictor
    return [_drive(1, 400, gap=True), _drive(2, 150), _drive(3, 260)]


def test_c213_half_angle_trig_equals_numpys_sin_and_cos():
    rng = np.random.default_rng(0)
    angles = np.concatenate([rng.uniform(-1000.0, 1000.0, 20000), rng.normal(0, 1e-3, 2000),
                             np.pi * np.arange(-40, 41) / 2, [0.0, -0.0, 1e-300, np.pi]])
    sin_a, cos_a = sin_cos(angles, exact=False)
    assert np.abs(sin_a - np.sin(angles)).max() < 1e-15
    assert np.abs(cos_a - np.cos(angles)).max() < 1e-15
    exact = sin_cos(angles)
    assert np.array_equal(exact[0], np.sin(angles)) and np.array_equal(exact[1], np.cos(angles))
    steps = np.concatenate([rng.normal(0, 0.3, 5000), rng.normal(0, 2e-3, 5000)])
    # the reference: the series of sin(a)/a and (1 - cos a)/a, in extended precision
    wide = steps.astype(np.longdouble)
    reference = [np.zeros_like(wide), np.zeros_like(wide)]
    term = np.ones_like(wide)
    for n in range(1, 30):  # term = a^(n-1) / n!
        if n % 2:
            reference[0] += term * (-1) ** (n // 2)
        else:
            reference[1] += term * (-1) ** (n // 2 - 1)
        term = term * wide / (n + 1)
    fast, slow = _sinc_terms(steps, exact=False), _sinc_terms(steps)
    for value, ref in zip(fast, reference):
        assert np.abs(value / ref - 1.0).max() < 1e-15
    # the exact form of (1 - cos a) / a loses digits to cancellation (the tangent's has none)
    assert np.abs(slow[0] / reference[0] - 1.0).max() < 1e-15
    assert np.abs(slow[1] / reference[1] - 1.0).max() < 1e-9
    assert np.array_equal(_sinc_terms(np.zeros(3), exact=False)[0], np.ones(3))


def test_c213_fit_rollouts_equal_the_exact_ones_to_rounding():
    rng = np.random.default_rng(1)
    shape = (4, 3000)
    v_x, v_y = rng.normal(1.0, 0.5, shape), rng.normal(0.0, 0.05, shape)
    omega = rng.normal(0.0, 1.0, shape)
    dt = rng.uniform(0.01, 0.05, shape)
    start = rng.normal(size=(4, 3))
    exact = rollout_columns(v_x, v_y, omega, dt, start)
    fast = rollout_columns(v_x, v_y, omega, dt, start, exact=False)
    for a, b in zip(exact, fast):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-11)
    for a, b in zip(body_increment(v_x, v_y, omega, dt),
                    body_increment(v_x, v_y, omega, dt, exact=False)):
        # the exact form's (1 - cos a) / a is the less precise one (cancellation)
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-14)
    tangents = [rng.normal(size=(3,) + shape) for _ in range(3)]
    a_idx = np.array([0, 10, 3001, 5000, 7000])
    b_idx = np.array([500, 10, 4000, 5999, 9000])
    poses, sums = window_tangents(v_x, v_y, omega, dt, *tangents, a_idx, b_idx)
    poses_f, sums_f = window_tangents(v_x, v_y, omega, dt, *tangents, a_idx, b_idx,
                                      exact=False)
    for a, b in zip(poses + sums, poses_f + sums_f):
        np.testing.assert_allclose(b, a, rtol=1e-10, atol=1e-10)


def _plan_per_drive(predictor, offset_ns):
    """Return the window plan searched drive by drive (what the one search reproduces)."""
    width = predictor.t_ns.shape[1]
    seg = predictor.segments
    plan = {key: np.zeros(len(seg), dtype=np.int64) for key in ('first', 'a', 'b')}
    plan.update(first_s=np.zeros(len(seg)), last_s=np.zeros(len(seg)))
    for d in np.unique(seg.drive):
        rows = np.nonzero(seg.drive == d)[0]
        stamps = predictor.t_ns[d, :predictor.sizes[d]]
        top = stamps.size - 1
        s_a = seg.t_a_ns[rows].astype(np.int64) - offset_ns
        s_b = seg.t_b_ns[rows].astype(np.int64) - offset_ns
        lo = np.searchsorted(stamps, s_a, side='right')
        hi = np.maximum(np.searchsorted(stamps, s_b, side='left'), lo)
        inner = hi > lo
        a = np.clip(lo, 0, top)
        b = np.where(inner, hi - 1, a)
        plan['first'][rows] = np.clip(lo - 1, 0, top) + d * width
        plan['a'][rows] = a + d * width
        plan['b'][rows] = b + d * width
        plan['first_s'][rows] = np.where(inner, stamps[a] - s_a, s_b - s_a) * 1e-9
        plan['last_s'][rows] = np.where(inner, s_b - stamps[b], 0) * 1e-9
    return plan


def test_c213_one_search_finds_every_window_as_a_search_per_drive_does(drives):
    segments = cut_segments(drives, SegmentOptions(horizon_m=0.3, horizon_rad=0.3))
    predictor = SegmentPredictor(drives, segments)
    assert len(set(predictor.sizes.tolist())) == 3 and len(segments) > 30
    rng = np.random.default_rng(2)
    # offsets inside a sample interval, on a stamp, beyond the drives' ends and far beyond
    offsets = [0, 1, -1, 35_000_000, -10**9, 10**10, -10**11, 5 * 10**12, -10**14]
    offsets += rng.integers(-2 * 10**9, 2 * 10**9, 40).tolist()
    for offset in offsets:
        expected = _plan_per_drive(predictor, offset)
        plan = predictor.plan(offset)
        for key, value in expected.items():
            assert np.array_equal(plan[key], value), (offset, key)


def _samples(drives, options):
    return pose_samples(drives, BASE, options)


def test_c214_the_lag_scan_reads_one_rollout_at_every_offset(drives):
    options = DiagnosisOptions()
    samples = _samples(drives, options)
    rollouts = model_rollouts(drives, samples, AugmentedModel(
        'edd_symmetric', ['time_offset']).bind(BASE, {'time_offset': {'offset_s': 0.0}}),
        options)
    for offset in (0.0, -0.07, 0.12, 0.4):
        source = AugmentedModel('edd_symmetric', ['time_offset']).bind(
            BASE, {'time_offset': {'offset_s': offset}})
        alone = pose_residuals(drives, samples, source, options)
        shared = pose_residuals(drives, samples, source, options, rollouts)
        assert np.array_equal(alone[0], shared[0]) and np.array_equal(alone[1], shared[1])
        assert alone[1].sum() > 100


def test_c214_the_differentiator_keeps_the_entries_it_uses(drives):
    drive = drives[0]
    t_ns, poses = drive.truth.t_ns, drive.truth.poses
    twist, valid = body_velocities(t_ns, poses, 0.25)
    index, operator, _ = _operator(t_ns, 0.25)
    coef = np.einsum('niw,nwc->nic', operator, poses[index])  # the whole product
    yaw = coef[:, 0, 2]
    world = coef[:, 1]
    assert np.array_equal(twist[:, 2], world[:, 2])
    assert np.array_equal(twist[:, 0], np.cos(yaw) * world[:, 0] + np.sin(yaw) * world[:, 1])
    assert np.array_equal(twist[:, 1], -np.sin(yaw) * world[:, 0] + np.cos(yaw) * world[:, 1])
    assert valid.sum() > 100


def test_c239_a_repeated_wheel_stamp_leaves_the_traced_signals_finite(drives):
    # every drive here repeats one wheel stamp (dt = 0): np.gradient divided by zero there
    from skidkin_ros.core.calibration.diagnosis.residuals import _signals
    for drive in drives:
        assert (np.diff(drive.wheels.t_ns) == 0).any()
        signals, _, _ = _signals(drive, drive.truth.t_ns, BASE, 0.5)
        # curvature is NaN by design below 0.05 m/s; every other signal is finite
        for name, values in signals.items():
            assert name == 'curvature' or np.isfinite(values).all(), name


def _play_reference(omega, dt_s, restart, half_play):
    """Return the wheel speeds sample by sample with the node's :func:`play_step`."""
    out = np.empty_like(omega)
    for r in range(omega.shape[0]):
        state = PLAY_STATE
        for i in range(omega.shape[1]):
            state, left, _ = play_step(state, half_play, float(dt_s[r, i - 1]) if i else 0.0,
                                       bool(i == 0 or restart[r, i]), float(omega[r, i]), 0.0)
            out[r, i] = left
    return out


def test_c243_the_play_loop_runs_once_for_the_same_speeds_and_play():
    """Check the stored play: the node's speeds bit for bit, the same arrays for equal inputs.

    A copy of the inputs finds the stored result; an input changed in place or another play
    is computed again.
    """
    rng = np.random.default_rng(4)
    shape = (3, 700)
    omega = np.cumsum(rng.normal(0.0, 0.4, shape), axis=1)
    omega[:, 200:210] = 0.0
    dt_s = rng.choice([0.0, 0.02, 0.05], shape, p=[0.05, 0.85, 0.1])
    restart = rng.random(shape) < 0.005
    backlash._RECENT.clear()
    calls = []
    real_row = backlash._row

    def counted(*args):
        calls.append(1)
        return real_row(*args)
    backlash._row = counted
    try:
        first = backlash.play_speeds(omega, dt_s, restart, 0.15)
        assert len(calls) == shape[0]
        assert np.array_equal(first[0], _play_reference(omega, dt_s, restart, 0.15))
        again = backlash.play_speeds(omega.copy(), dt_s.copy(), restart.copy(), 0.15)
        assert len(calls) == shape[0] and again[0] is first[0] and again[1] is first[1]
        with pytest.raises(ValueError):
            again[0][0, 0] = 1.0  # what is handed out again cannot be changed by a caller
        omega[1, 300] += 0.5  # the same array, changed in place: computed again
        moved = backlash.play_speeds(omega, dt_s, restart, 0.15)
        assert len(calls) == 2 * shape[0]
        assert np.array_equal(moved[0], _play_reference(omega, dt_s, restart, 0.15))
        other = backlash.play_speeds(omega, dt_s, restart, 0.2)
        assert len(calls) == 3 * shape[0]
        assert np.array_equal(other[0], _play_reference(omega, dt_s, restart, 0.2))
        assert not np.array_equal(other[0], moved[0])
    finally:
        backlash._row = real_row
        backlash._RECENT.clear()


@pytest.mark.parametrize('window', [True, False])
def test_c244_the_residual_levels_take_each_folds_rows_once(drives, window, monkeypatch):
    """The level scores equal those of the rows taken again for every level, bit for bit.

    Both forms of the terms: as the smoothed target sees them (the default, the yaw rate with
    terms of its own) and read at the pose.
    """
    monkeypatch.setattr(regression, 'WINDOW_TERMS', window)
    options = DiagnosisOptions(interval='ending')
    samples = pose_samples(drives, BASE, options)
    fit = fit_residual_model(drives, samples, BASE, options)
    twist, rate = model_inputs(drives, samples, BASE, options)
    ok = np.all(np.isfinite(twist), axis=1) & np.all(np.isfinite(rate), axis=1)
    if window:
        ranges = _ranges(twist[ok & samples.valid], rate[ok & samples.valid])
        target, valid, moving, turning = window_terms(drives, samples, BASE, options, ranges,
                                                      options.smoothing_s)
        ok &= np.all(np.isfinite(moving), axis=1) & np.all(np.isfinite(turning), axis=1)
    else:
        target, valid = pose_residuals(drives, samples, BASE, options)
    rows = np.nonzero(ok & valid & np.all(np.isfinite(target), axis=1))[0]
    if window:
        terms_of = (moving[rows], moving[rows], turning[rows])
    else:
        phi = residual.features(_ranges(twist[rows], rate[rows]), twist[rows], rate[rows])
        terms_of = (phi, phi, phi)
    folds = block_folds(samples.drive[rows], samples.t_ns[rows])
    for c, (out, _) in enumerate(residual.OUTPUTS):
        y = target[rows, c]
        phi_all = terms_of[c]
        for level in residual.LEVELS:
            cols = [j for j, (_, lvl, _, _) in enumerate(residual.TERMS) if lvl <= level]
            score = 0.0
            for fold in range(BLOCK_FOLDS):
                test = folds == fold
                if test.any() and not test.all():
                    score += blr(phi_all[~test][:, cols], y[~test]).log_likelihood(
                        phi_all[test][:, cols], y[test])
            assert fit.scores[out][level] == score
    assert any(level > 0 for level in fit.levels)  # the base model leaves a residual to fit


def test_c244_the_correction_sums_the_terms_as_the_node_does():
    """C phi from one contiguous copy equals the term-by-term sum of the strided terms."""
    rng = np.random.default_rng(5)
    count = len(residual.TERMS)
    coef = rng.normal(0.0, 0.1, 3 * count).tolist()
    coef[4] = 0.0
    for shape in ((count,), (2, 300, count)):
        phi = rng.uniform(-1.0, 1.0, shape)
        phi[..., 7] = -0.0
        reference = []
        for o in range(3):
            total = phi[..., 0] * coef[o * count]
            for j in range(1, count):
                total = total + phi[..., j] * coef[o * count + j]
            reference.append(total)
        fast = residual.correction(coef, phi)
        assert fast.shape == shape[:-1] + (3,)
        assert np.stack(reference, axis=-1).tobytes() == fast.tobytes()
    sample = phi[1, 17].tolist()
    assert residual.scalar_correction(coef, sample) == tuple(fast[1, 17].tolist())


def test_c283_the_shared_lag_rule_gives_the_diagnosis_its_old_scan_bit_for_bit(drives):
    # the scan the diagnosis ran before its rule moved to core/calibration/lag.py (shared with
    # the online delay check), written out here: the same lags, costs and best lag
    from skidkin_ros.core.calibration.diagnosis.state import ModelState
    from skidkin_ros.core.calibration.diagnosis.tracing import lag_scan
    options = DiagnosisOptions()
    samples = _samples(drives, options)
    state = ModelState((), {'alpha': 0.9, 'b_hat': 0.8}, {})
    best, (lags, curve) = lag_scan(drives, samples, state, 'edd_symmetric', GEOM, options)
    base = state.bind('edd_symmetric', GEOM)
    scale = np.array([1.0, 1.0, GEOM.track_width / 2])
    rollouts = model_rollouts(drives, samples, AugmentedModel(
        'edd_symmetric', ['time_offset']).bind(base, {'time_offset': {'offset_s': 0.0}}),
        options)
    scores = {}

    def cost(lag):
        lag = round(lag / 0.01) * 0.01
        if lag not in scores:
            source = AugmentedModel('edd_symmetric', ['time_offset']).bind(
                base, {'time_offset': {'offset_s': float(lag)}})
            residual_, valid = pose_residuals(drives, samples, source, options, rollouts)
            scores[lag] = float(np.mean(((residual_[valid] * scale) ** 2).sum(axis=1)))
        return scores[lag]

    reach = round(options.lag_range_s / 0.05)
    coarse_best = min((k * 0.05 for k in range(-reach, reach + 1)), key=cost)
    for k in range(-4, 5):
        if abs(coarse_best + k * 0.01) <= options.lag_range_s + 1e-9:
            cost(coarse_best + k * 0.01)
    old_lags = np.array(sorted(scores))
    old_curve = np.array([scores[lag] for lag in old_lags])
    assert np.array_equal(lags, old_lags) and np.array_equal(curve, old_curve)
    assert best == float(old_lags[int(np.argmin(old_curve))])
