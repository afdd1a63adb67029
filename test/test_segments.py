"""Segment cutting on the ground-truth path and the padded integrator arrays."""

from _calib_synth import GEOMETRY, make_drive
import numpy as np
import pytest

from skidkin_ros.core.calibration.fitting import segment_errors
from skidkin_ros.core.calibration.segments import cut_segments, SegmentOptions, usable_segments
from skidkin_ros.core.drive import Drive, PoseTrack, WheelSamples
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.errors import DataError


def _straight(speed_m_s=0.5, duration_s=20.0, truth_dt_s=0.1, wheel_dt_s=0.03,
              stop=None):
    t_truth = np.arange(0.0, duration_s + 1e-9, truth_dt_s)
    x = speed_m_s * t_truth
    if stop is not None:
        x = np.where(t_truth < stop[0], x, np.where(t_truth < stop[1], speed_m_s * stop[0],
                                                    speed_m_s * (t_truth - stop[1] + stop[0])))
    t_w = np.arange(0.0, duration_s + 1e-9, wheel_dt_s)
    omega = np.full(t_w.shape, speed_m_s / GEOMETRY.wheel_radius)
    truth = PoseTrack((t_truth * 1e9).round(), x, np.zeros_like(x), np.zeros_like(x))
    return Drive('line', WheelSamples((t_w * 1e9).round(), omega, omega.copy() + 0.01), truth)


def test_segments_follow_the_truth_path_and_do_not_overlap():
    segs = cut_segments([_straight()], SegmentOptions(horizon_m=2.0))
    assert len(segs) == 5  # 10 m of driving
    assert np.all(segs.path_m >= 2.0 - 1e-9) and np.all(segs.path_m < 2.1)
    np.testing.assert_array_equal(segs.t_a_ns[1:], segs.t_b_ns[:-1])


def test_padded_arrays_hold_the_last_wheel_sample():
    drive = _straight()
    segs = cut_segments([drive], SegmentOptions(horizon_m=2.0))
    # step durations add up to the segment duration; padding has dt = 0
    np.testing.assert_allclose(segs.dt_s.sum(axis=1), segs.duration_s, atol=1e-12)
    i = 1
    t_a = segs.t_a_ns[i]
    held = np.searchsorted(drive.wheels.t_ns, t_a, side='right') - 1
    assert drive.wheels.t_ns[held] <= t_a
    assert segs.omega_r[i, 0] == drive.wheels.omega_r[held]
    first_inner = drive.wheels.t_ns[held + 1]
    assert segs.dt_s[i, 0] == pytest.approx((first_inner - t_a) * 1e-9)
    steps = segs.step_counts[i]
    assert np.all(segs.dt_s[i, steps:] == 0.0)


def test_true_model_reproduces_the_truth_on_segments():
    drive = make_drive('edd_symmetric', duration_s=60.0, seed=4)
    segs = cut_segments([drive], SegmentOptions(horizon_m=1.0, horizon_rad=1.0))
    model = get_model('edd_symmetric')
    k = model.vector({'alpha': 0.9, 'b_hat': 1.04}, GEOMETRY)
    err = segment_errors(model, k, GEOMETRY, segs)
    assert len(segs) > 10
    assert np.abs(err).max() < 1e-9


def test_stationary_segments_are_dropped_and_counted():
    """C13: no motion, zero commands: excluded from fitting, counted."""
    still = PoseTrack(np.arange(0, 10) * 100_000_000, np.zeros(10), np.zeros(10), np.zeros(10))
    zeros = np.zeros(30)
    wheels = WheelSamples(np.arange(30) * 33_000_000, zeros, zeros)
    drives = [Drive('still', wheels, still), _straight()]
    segs = cut_segments(drives, SegmentOptions(horizon_m=2.0))
    assert segs.counts.stationary == 1
    assert len(segs) == 5 and np.all(segs.drive == 1)


def test_short_drives_whole_or_dropped():
    short = _straight(duration_s=2.0)  # 1 m < h
    whole = cut_segments([short], SegmentOptions(horizon_m=2.0))
    assert len(whole) == 1 and whole.counts.whole_drive == 1
    assert whole.path_m[0] == pytest.approx(1.0)
    dropped = cut_segments([short], SegmentOptions(horizon_m=2.0, short_drive='drop'))
    assert len(dropped) == 0


def test_invalid_truth_and_time_horizon():
    drive = _straight()
    valid = np.ones(len(drive.truth), bool)
    valid[50] = False
    truth = PoseTrack(drive.truth.t_ns, drive.truth.x, drive.truth.y, drive.truth.yaw, valid)
    segs = cut_segments([Drive('x', drive.wheels, truth)], SegmentOptions(horizon_m=2.0))
    assert segs.counts.invalid_truth == 1 and len(segs) == 4
    timed = cut_segments([drive], SegmentOptions(horizon_s=5.0))
    np.testing.assert_allclose(timed.duration_s, 5.0)


def test_no_truth_is_an_error():
    drive = _straight()
    with pytest.raises(DataError, match='ground truth'):
        cut_segments([Drive('x', drive.wheels, None)])


def test_too_few_segments_say_how_many_who_needs_more_and_what_to_do():
    drive = _straight(duration_s=5.0)  # 2.5 m: one segment of 2 m
    with pytest.raises(DataError, match=r'^1 usable training segment\(s\) out of 1 drive\(s\) '
                       r"\(\{'kept': 1.*a diagnosis needs at least 6: drive further than the "
                       'horizon 2 m with ground truth'):
        usable_segments([drive], SegmentOptions(horizon_m=2.0), 'training', 6, 'a diagnosis')
    assert len(usable_segments([drive], SegmentOptions(horizon_m=2.0), 'training')) == 1
    with pytest.raises(DataError, match='no evaluation drive given'):
        usable_segments([], SegmentOptions(), 'evaluation')
