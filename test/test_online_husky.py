"""Online calibration on the real Husky windows: the bench's machinery, and a bound it kept."""

from lab.studies.online_husky import (GEOMETRY, HORIZON, ideal_file, learned_at, load_windows,
                                      offline_file, reference_of, run_stream, score,
                                      with_values)
import numpy as np
import pytest
from skidkin_ros.core.online import online_odometer
from skidkin_ros.core.online.window import _toward_bounds

ONLINE = {'online.enabled': True, 'online.horizon': HORIZON[0],
          'online.horizon_rad': HORIZON[1]}


@pytest.fixture(scope='module')
def husky():
    windows = load_windows(limit=60)
    return windows, offline_file(windows)


def test_the_windows_stream_in_time_order_and_the_reference_drops_held_repeats(husky):
    windows, _ = husky
    starts = [int(w.drive.wheels.t_ns[0]) for w in windows]
    assert all(b - a >= 3_900_000_000 for a, b in zip(starts, starts[1:]))
    ref = reference_of(windows[5])
    rows = windows[5].drive.wheels.t_ns
    # about 10 Hz out of the 20 Hz rows; no two consecutive poses equal
    assert 0.3 * len(rows) < len(ref) < 0.7 * len(rows)
    same = ((np.diff(ref.x) == 0) & (np.diff(ref.y) == 0) & (np.diff(ref.yaw) == 0))
    assert not same.any()
    # each kept pose is stamped on a row of the table
    assert set(ref.t_ns.tolist()) <= set(rows.tolist())


def test_online_learns_the_separation_from_the_ideal_file_on_60_windows(husky):
    windows, calibrated = husky
    ideal = ideal_file(calibrated)
    run = run_stream('online', with_values(ideal, ONLINE), windows)
    fixed = run_stream('ideal', ideal, windows)
    # The yaw rate per wheel speed difference is r alpha / b_hat: ideal 1 / 0.555 m; the
    # calibrator's file on these windows about 0.9 / 1.16 m (the Husky turns half as much as
    # ideal differential drive predicts). alpha alone follows each command's slip (it swings
    # from window to window); the separation per alpha is what turning teaches.
    per_alpha = np.median([v['b_hat'] / v['alpha'] for v in run.values[-30:]])
    offline = calibrated.model_values['edd_symmetric']
    assert per_alpha > 1.8 * GEOMETRY.track_width
    assert 0.8 < per_alpha / (offline['b_hat'] / offline['alpha']) < 1.5
    assert run.counters['online_segments'] > 30
    held = [w.index for w in windows if w.held_out]
    online_s = score(run, windows, held, calibrated['interval'], False)
    ideal_s = score(fixed, windows, held, calibrated['interval'], False)
    assert np.median(online_s.eps_theta) < 0.5 * np.median(ideal_s.eps_theta)


def test_the_reference_never_reaches_a_windows_past(husky):
    """Cutting window 7's reference at its middle changes nothing before the cut."""
    windows, calibrated = husky
    config = with_values(calibrated, ONLINE)
    odometer_a, odometer_b = online_odometer(config), online_odometer(config)
    for w in windows[:7]:
        for odometer in (odometer_a, odometer_b):
            odometer.predict(w.drive.wheels, w.drive.truth.poses[0], reference=reference_of(w))
    w = windows[7]
    ref = reference_of(w)
    middle = int(w.drive.wheels.t_ns[20])
    keep = ref.t_ns <= middle
    cut = type(ref)(ref.t_ns[keep], ref.x[keep], ref.y[keep], ref.yaw[keep])
    full = odometer_a.predict(w.drive.wheels, w.drive.truth.poses[0], reference=ref)
    part = odometer_b.predict(w.drive.wheels, w.drive.truth.poses[0], reference=cut)
    before = w.drive.wheels.t_ns <= middle
    np.testing.assert_array_equal(full.poses[before], part.poses[before])
    np.testing.assert_array_equal(full.pose_covariances[before], part.pose_covariances[before])


def test_learned_at_finds_where_online_stays_within_the_offline_error():
    offline = np.ones(100)
    online = np.concatenate([np.full(30, 3.0), np.ones(70)])
    at = learned_at(online, offline, run=10)
    assert at is not None and 21 <= at <= 30
    assert learned_at(np.full(100, 2.0), offline, run=10) is None


def test_a_step_past_a_bound_stops_half_way_to_it_c269():
    lo, hi = np.array([0.0, 1e-6]), np.array([1.0, np.inf])
    k0 = np.array([0.9, 0.6])
    # b_hat asked to go to -0.4: half the way to 0 instead; alpha takes its step (C289)
    k = _toward_bounds(k0, np.array([0.8, -0.4]), lo, hi)
    np.testing.assert_allclose(k, [0.8, 0.6 - 0.5 * (0.6 - 1e-6)])
    # inside the range: the step as is
    np.testing.assert_array_equal(_toward_bounds(k0, np.array([0.8, 0.7]), lo, hi), [0.8, 0.7])
    # a parameter already on its bound is clipped and does not hold the others back
    np.testing.assert_array_equal(
        _toward_bounds(np.array([1.0, 0.6]), np.array([1.2, 0.7]), lo, hi), [1.0, 0.7])


def test_a_parameter_pushed_to_its_bound_does_not_hold_the_others_back_c289():
    """A lag whose truth is its bound (0) keeps being pushed there: the others still learn.

    Cutting the whole step to half the way to the bound halved the room every update and with
    it every other parameter's step: alpha, 0.4 off, moved 0.02 in total in 30 updates.
    """
    lo, hi = np.array([0.0, 0.0]), np.array([2.0, 1.0])
    k = np.array([0.01, 0.5])        # tau_s near 0, alpha 0.4 below its truth
    for _ in range(30):
        target = np.array([-0.01, 0.9])     # the window's optimum: tau_s just below 0
        step = np.clip(target - k, -0.05, 0.05)    # the step limit (prior_sigma)
        k = _toward_bounds(k, k + step, lo, hi)
    assert k[1] == pytest.approx(0.9)
    assert 0.0 <= k[0] < 1e-3


def test_online_from_the_ideal_file_never_drives_b_hat_to_its_bound_c269(husky):
    """Real data, ideal start, windows 80-99: b_hat went to 0.065 m on the first segment.

    Window 80 starts with the ICP pose frozen for 0.3 s, then catching up 0.6 rad in 0.15 s
    (the gyro says 0.09 rad): one Gauss-Newton step on that segment took b_hat from 0.555 m
    past 0 (clipped to its bound, 0.065 with the half-way rule alone); the wheels then turned
    ten times too fast and every later pose that turned was refused as a jump (230 of 454):
    nothing was learned again.
    """
    _, calibrated = husky
    windows = load_windows(limit=100)[80:]
    run = run_stream('online', with_values(ideal_file(calibrated), ONLINE), windows)
    assert min(v['b_hat'] for v in run.values) > 0.15
    assert run.counters.get('reference_jump', 0) < 0.02 * run.counters['reference_accepted']
    assert run.counters['online_step_limited'] >= 1


@pytest.mark.heavy
def test_online_on_all_husky_windows_reaches_the_calibrated_file():
    """All 603 windows (about a minute): online from the ideal file ends near the offline fit."""
    windows = load_windows()
    calibrated = offline_file(windows)
    ideal = ideal_file(calibrated)
    run = run_stream('online', with_values(ideal, ONLINE), windows)
    held = [w.index for w in windows if w.held_out]
    online_s = score(run, windows, held, calibrated['interval'], False)
    cal_run = run_stream('calibrated', calibrated, windows)
    cal_s = score(cal_run, windows, held, calibrated['interval'], True)
    assert min(v['b_hat'] for v in run.values) > 0.1
    assert np.median(online_s.eps_t) < 1.1 * np.median(cal_s.eps_t)
    assert np.median(online_s.eps_theta) < 1.1 * np.median(cal_s.eps_theta)
    # the fixed calibrated file's NEES at the window ends: what skidkin evaluate reports
    assert 1.5 < np.mean(cal_s.nees) < 2.5
