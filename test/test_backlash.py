"""The backlash extension: the play a motor turns through after a reversal, as a wheel state."""

import numpy as np
import pytest
from skidkin_ros.core.kinematics.augmented import AugmentedModel
from skidkin_ros.core.kinematics.backlash import play_speeds, PLAY_STATE, play_step
from skidkin_ros.core.kinematics.specs import Geometry

GEOM = Geometry(wheel_radius=0.1651, track_width=0.555)


def _steps(t_ns, max_dt_s=0.5):
    dt = np.zeros((1, len(t_ns)))
    dt[:, :-1] = np.diff(np.asarray(t_ns, dtype=np.int64)[None], axis=1) * 1e-9
    restart = np.zeros(dt.shape, bool)
    restart[:, 1:] = dt[:, :-1] > max_dt_s
    dt[dt > max_dt_s] = 0.0
    return dt, restart


def test_a_reversal_loses_the_play_and_a_constant_period_gives_the_exact_mean():
    """Forward 3 s, back 3 s at 2 rad/s, 20 Hz: the play is lost at each reversal.

    The wheel turns play/2 less at the start (it starts centred), a whole play less after the
    reversal, nothing else.
    """
    t_ns = np.arange(120) * 50_000_000
    omega = np.where(np.arange(120) < 60, 2.0, -2.0)[None]
    dt, restart = _steps(t_ns)
    play = 0.3
    wheel, _ = play_speeds(omega, dt, restart, play / 2)
    forward = float(np.sum(wheel[0, :60] * 0.05))
    backward = float(np.sum(wheel[0, 60:119] * 0.05))
    assert forward == pytest.approx(6.0 - play / 2, abs=1e-12)
    assert backward == pytest.approx(-(5.9 - play), abs=1e-12)
    # the wheel stands while the motor crosses the play (0.3 rad: three samples of 0.1 rad),
    # then follows it exactly
    assert np.abs(wheel[0, 60:63]).max() < 1e-12 and np.all(wheel[0, 63:119] == -2.0)


def test_the_node_form_equals_the_batch_form_bit_for_bit():
    """Random speeds with reversals, an uneven period, a repeated stamp and a gap."""
    rng = np.random.default_rng(1)
    n = 500
    t_ns = np.cumsum(rng.integers(40_000_000, 60_000_000, n)).astype(np.int64)
    t_ns[100] = t_ns[99]
    t_ns[300:] += 2_000_000_000
    wl = np.sin(np.arange(n) * 0.05) * 3 + rng.normal(0, 0.2, n)
    wr = np.sin(np.arange(n) * 0.07 + 1) * 3
    model = AugmentedModel('edd_symmetric', ['backlash', 'lateral_skid', 'first_order_lag',
                                             'residual_model'])
    bound = model.bind({'alpha': 0.9, 'b_hat': 1.1},
                       {'backlash': {'play_rad': 0.5}, 'lateral_skid': {'k': 0.05},
                        'first_order_lag': {'tau_s': 0.1}}, GEOM)
    dt, restart = _steps(t_ns)
    _, mean = bound.intervals(t_ns[None], wl[None], wr[None], dt, restart)
    state, rows = None, []
    for i in range(n):
        state, _ = bound.begin(state, int(t_ns[i]), float(wl[i]), float(wr[i]),
                               bool(restart[0, i]))
        state, twist = bound.advance(state, float(dt[0, i]))
        rows.append(twist)
    assert np.array_equal(np.array(rows), mean[0])
    # the play matters here: without it the twists differ
    plain = model.bind({'alpha': 0.9, 'b_hat': 1.1},
                       {'lateral_skid': {'k': 0.05}, 'first_order_lag': {'tau_s': 0.1}}, GEOM)
    assert np.abs(plain.intervals(t_ns[None], wl[None], wr[None], dt, restart)[1]
                  - mean).max() > 0.1


def test_no_play_changes_nothing_and_a_gap_restarts_centred():
    state, left, right = play_step(PLAY_STATE, 0.0, 0.05, False, 1.5, -2.0)
    assert (left, right) == (1.5, -2.0)
    # after a gap the state is centred again: the first interval does not move a wheel with play
    state, left, right = play_step((0.1, -0.1, 1.0, -1.0, 0.05), 0.1, 3.0, True, 1.0, -1.0)
    assert (left, right) == (0.0, 0.0) and state[:2] == (0.0, 0.0)


def test_the_diagnosis_finds_a_backlash_where_a_lag_stood_in():
    """A drivetrain play of 0.4 rad (the study's field effect, C204) is found as a backlash.

    The diagnosis adds ``backlash`` with about that play (in encoder radians: the wheel's play
    over alpha), not the lag or time offset that stand in for it without the extension, and the
    forward speed's first lead in the trace is the history signal reversal_speed.
    """
    from lab.studies.effects import GEOMETRY as SIM_GEOMETRY, SIM_INTERVAL, TRUE_PARAMS
    from lab.studies.unnamed_effects import drives, SmoothEffect
    from skidkin_ros.core.calibration.diagnosis import diagnose, DiagnosisOptions
    from skidkin_ros.core.calibration.fitting import fit_model
    from skidkin_ros.core.calibration.segments import cut_segments

    effect = SmoothEffect('field_backlash', 0.4, {}, 'backlash', ())
    train = drives((effect,), [3001, 3002], 60.0, 'plain')
    evaluate = drives((effect,), [3003], 60.0, 'plain')
    options = DiagnosisOptions(interval=SIM_INTERVAL,
                               candidates=('time_offset', 'first_order_lag', 'backlash'))
    base = fit_model('edd_symmetric', SIM_GEOMETRY, cut_segments(train, options.train_segments()))
    result = diagnose(train, evaluate, SIM_GEOMETRY, {'edd_symmetric': base.values},
                      'edd_symmetric', options)
    assert result.extensions == ('backlash',)
    play = result.final.ext_values['backlash']['play_rad']
    assert play == pytest.approx(0.4 / TRUE_PARAMS['alpha'], rel=0.25)
    assert result.steps[-1].stats_t.median < 0.7 * result.steps[1].stats_t.median
    forward = [signal for component, signal, _ in result.trace.top(40) if component == 'v_x']
    assert forward[0] == 'reversal_speed', result.trace.top(8)
