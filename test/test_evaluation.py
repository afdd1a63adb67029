"""Relative errors per metre, hold-out splits and the h_t x h_e study."""

from dataclasses import replace

from _calib_synth import GEOMETRY, make_drive
import numpy as np
import pytest

from skidkin_ros.core.calibration.evaluation import ErrorStats, evaluate_models
from skidkin_ros.core.calibration.holdout import split_holdout
from skidkin_ros.core.calibration.pipeline import CalibrationOptions, horizon_study
from skidkin_ros.core.calibration.segments import cut_segments, SegmentOptions
from skidkin_ros.errors import DataError, ParameterError


def test_eps_t_of_a_scale_error_on_straight_driving():
    # truth slips 10 %: the ideal model overshoots by 1/0.9 - 1 of the path, and never turns
    drive = make_drive('edd_symmetric', {'alpha': 0.9, 'b_hat': 1.0}, kind='straight',
                       duration_s=60.0, rate_hz=20.0, truth_every=2)
    segs = cut_segments([drive], SegmentOptions(horizon_m=2.0))
    table = evaluate_models({'ideal_dd': {}, 'edd_symmetric': {'alpha': 0.9, 'b_hat': 1.0}},
                            GEOMETRY, segs)
    # segments driven in one direction: the overshoot is exactly 1/0.9 - 1 per metre
    active = segs.dt_s > 0
    forward = np.all((segs.omega_l > 0) | ~active, axis=1)
    backward = np.all((segs.omega_l < 0) | ~active, axis=1)
    one_way = forward | backward
    assert one_way.sum() >= 3
    np.testing.assert_allclose(table['ideal_dd'].eps_t[one_way], 1 / 0.9 - 1, rtol=1e-6)
    # a reversal inside a segment partly cancels the overshoot, never adds to it
    assert np.all(table['ideal_dd'].eps_t <= 1 / 0.9 - 1 + 1e-9)
    np.testing.assert_allclose(table['ideal_dd'].eps_theta_deg, 0.0, atol=1e-9)
    assert table['edd_symmetric'].stats_t.median < 1e-9
    assert table['ideal_dd'].stats_t.count == len(segs)


def test_eps_theta_in_degrees_per_metre():
    drive = make_drive('edd_symmetric', {'alpha': 0.9, 'b_hat': 1.0}, duration_s=120.0,
                       rate_hz=20.0, truth_every=2, seed=3)
    segs = cut_segments([drive], SegmentOptions(horizon_m=2.0))
    ev = evaluate_models({'ideal_dd': {}}, GEOMETRY, segs)['ideal_dd']
    manual = np.degrees(np.abs(ev.errors[ev.scored, 2])) / segs.path_m[ev.scored]
    np.testing.assert_allclose(ev.eps_theta_deg, manual)
    assert ev.stats_theta.median > 1.0


def test_error_stats():
    stats = ErrorStats.of(np.arange(1.0, 101.0))
    assert stats.median == pytest.approx(50.5) and stats.count == 100
    assert stats.q25 == pytest.approx(25.75) and stats.p90 == pytest.approx(90.1)
    assert ErrorStats.of(np.array([])).count == 0


def _windows(n):
    drives = []
    for i in range(n):
        d = make_drive(duration_s=10.0, rate_hz=10.0, seed=i, name=f'w{i}')
        drives.append(type(d)(d.name, d.wheels, d.truth, meta={'calib_step': i // 2}))
    return drives


def test_split_by_key_even_odd():
    train, evaluate = split_holdout(_windows(8), every=2, key='calib_step')
    assert [d.meta['calib_step'] % 2 for d in train] == [0] * 4
    assert [d.meta['calib_step'] % 2 for d in evaluate] == [1] * 4


def test_split_by_drive_and_by_time_deterministic_and_disjoint():
    drives = _windows(9)
    train, evaluate = split_holdout(drives, every=3)
    assert [d.name for d in evaluate] == ['w2', 'w5', 'w8'] and len(train) == 6
    long_drive = make_drive(duration_s=100.0, rate_hz=10.0)
    train, evaluate = split_holdout([long_drive], every=2, mode='time', block_s=20.0)
    again = split_holdout([long_drive], every=2, mode='time', block_s=20.0)
    assert [d.name for d in evaluate] == [d.name for d in again[1]]
    train_t = np.concatenate([d.wheels.t_ns for d in train])
    eval_t = np.concatenate([d.wheels.t_ns for d in evaluate])
    assert not set(train_t) & set(eval_t)
    assert train_t.size + eval_t.size == len(long_drive.wheels)
    with pytest.raises(ParameterError):
        split_holdout(drives, every=1)
    with pytest.raises(DataError, match='calib_step'):
        split_holdout([long_drive], key='calib_step')


def test_horizon_study_fills_its_grid():
    train = [make_drive('edd_symmetric', duration_s=150.0, rate_hz=20.0, truth_every=2, seed=1)]
    evaluate = [make_drive('edd_symmetric', duration_s=100.0, rate_hz=20.0, truth_every=2,
                           seed=2)]
    study = horizon_study(train, evaluate, GEOMETRY,
                          CalibrationOptions(models=('edd_symmetric',)), [1.0, 3.0],
                          [0.5, 2.0, 4.0])
    grid = study.median['edd_symmetric']
    assert grid.shape == (2, 3) and np.all(np.isfinite(grid))
    # noise-free data from the same model: every horizon pair fits almost exactly
    assert np.all(grid < 0.02)


@pytest.mark.parametrize('interval', ['ending', 'midpoint'])
def test_horizon_study_cuts_the_segments_the_main_fit_cuts(monkeypatch, interval):
    # the study must cut its segments as calibrate does (the sample-interval convention
    # included), changing only the horizon
    from skidkin_ros.core.calibration import pipeline
    train = [make_drive('edd_symmetric', duration_s=60.0, rate_hz=20.0, truth_every=2, seed=1)]
    evaluate = [make_drive('edd_symmetric', duration_s=40.0, rate_hz=20.0, truth_every=2,
                           seed=2)]
    options = CalibrationOptions(models=('edd_symmetric',), interval=interval, n_starts=1)
    cut = []

    def spy(drives, seg_opts):
        segments = cut_segments(drives, seg_opts)
        cut.append((seg_opts, segments))
        return segments

    monkeypatch.setattr(pipeline, 'cut_segments', spy)
    horizon_study(train, evaluate, GEOMETRY, options, [1.5], [0.5])
    main_train = replace(options, h_t=1.5).train_segments()
    main_eval = replace(options, h_e=0.5).eval_segments()
    assert {c[0] for c in cut} == {main_train, main_eval}
    for seg_opts, segments in cut:
        drives = train if seg_opts == main_train else evaluate
        expected = cut_segments(drives, seg_opts)
        np.testing.assert_array_equal(segments.omega_l, expected.omega_l)
        np.testing.assert_array_equal(segments.omega_r, expected.omega_r)
        # and the convention shows in the held speeds: ending and midpoint differ
        other = cut_segments(drives, replace(seg_opts, interval='starting'))
        assert not np.array_equal(segments.omega_l, other.omega_l)
