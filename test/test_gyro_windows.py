"""Held-out windows of the gyro's noise calibration on ground truth stamped off the wheel samples.

A lidar's poses are stamped at the end of each sweep, never on a wheel sample: the windows that
calibrate adapt's heading noise (and score the NEES of evaluate --imu-mode) used to need both
ends on wheel samples, so a bag gave none and the demo warned "0 held-out segments start and end
on wheel samples". Now each end goes to the nearest wheel sample and the truth is interpolated
there (C180).
"""

from dataclasses import replace

import numpy as np
from skidkin_ros.core.calibration.gyro_fit import run_windows, segment_windows, window_poses
from skidkin_ros.core.calibration.segments import cut_segments, SegmentOptions
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.sim.simulate import SimConfig, simulate

MS = 1_000_000


def _drives():
    config = SimConfig(duration_s=40.0, seed=4)
    sim = simulate(config)
    grid = sim.drive('grid')  # truth on the wheel samples, as a table has it
    # 10 Hz sweeps ending 99.7 ms after they start: the demo's lidar, 50 ms wheel samples
    t = sim.start_ns + np.arange(1, 390) * 100 * MS + 99_700_000
    t = t[t < grid.wheels.t_ns[-1]]
    poses = sim.pose_at(t)
    lidar = replace(grid, truth=PoseTrack(t, poses[:, 0], poses[:, 1], poses[:, 2]))
    flat = {'model': config.true_model, 'interval': 'midpoint',
            **{f'models.{config.true_model}.{k}': v for k, v in config.true_params.items()}}
    return grid, lidar, OdometryConfig.from_flat(flat)


def test_c180_windows_run_on_ground_truth_stamped_off_the_wheel_samples():
    grid, lidar, config = _drives()
    options = SegmentOptions(horizon_m=2.0, interval='midpoint')
    medians, moved = {}, False
    for name, drive in (('grid', grid), ('lidar', lidar)):
        segments = cut_segments([drive], options)
        windows = segment_windows([drive], segments)
        assert len(windows.get(0, [])) >= 5, name
        t = drive.wheels.t_ns
        for i, j, k in windows[0]:
            # each end within half a wheel period of its segment's end
            assert abs(int(t[i]) - int(segments.t_a_ns[k])) <= 25 * MS
            assert abs(int(t[j]) - int(segments.t_b_ns[k])) <= 25 * MS
            start, end = window_poses(drive, segments, (i, j, k))
            if name == 'grid':  # on the wheel samples: the segment's own poses, unchanged
                assert np.array_equal(start, segments.start[k])
                assert np.array_equal(end, segments.end[k])
            else:  # the truth at the wheel sample, not at the segment's (off-grid) stamp
                assert np.array_equal(start, lidar.truth.interpolate(t[i]))
                assert np.array_equal(end, lidar.truth.interpolate(t[j]))
                moved = moved or not np.array_equal(start, segments.start[k])
        errors, covs, _ = run_windows(config, [drive], segments, windows)
        assert errors.shape == (len(windows[0]), 3) and np.all(np.isfinite(covs))
        medians[name] = float(np.median(np.hypot(errors[:, 0], errors[:, 1])))
    assert moved  # the off-grid case did move the window ends
    # The true model from the true pose: the error is the encoders' noise, on either truth
    # (interpolating 10 Hz poses costs well under a millimetre at these speeds).
    assert medians['grid'] < 0.01
    assert medians['lidar'] < 2 * medians['grid'] + 0.002


def test_covariances_read_at_the_window_ends_only_are_the_same():
    """Reading the covariance out at the window ends only changes none of the numbers."""
    grid, _, config = _drives()
    assert grid.imu is not None
    prefix = f'models.{config.model}.noise.'
    flat = {**config.values, 'imu.mode': 'adapt', prefix + 'calibrated': True,
            prefix + 'var_x_const': 1e-4, prefix + 'var_yaw_per_s': 1e-5}
    adapt = OdometryConfig.from_flat(flat)
    assert adapt.active_noise is not None
    segments = cut_segments([grid], SegmentOptions(horizon_m=2.0, interval='midpoint'))
    windows = segment_windows([grid], segments)
    full = run_windows(adapt, [grid], segments, windows)
    ends = run_windows(adapt, [grid], segments, windows, ends_only=True)
    assert np.array_equal(full[0], ends[0]) and np.array_equal(full[1], ends[1])
    assert np.all(np.isfinite(full[1])) and np.any(full[1][:, 2, 2] > 0.0)
    j = [j for _, j, _ in windows[0]]
    a, b = full[2][0], ends[2][0]
    assert np.array_equal(a.poses, b.poses)
    assert np.array_equal(a.covariances[j], b.covariances[j])
    assert np.array_equal(a.imu_gain[j], b.imu_gain[j])
    assert np.array_equal(a.pose_covariances[j], b.pose_covariances[j])
    others = np.setdiff1d(np.arange(len(a.poses)), j)
    assert np.all(np.isnan(b.covariances[others])) and np.all(np.isfinite(a.covariances))


def test_c191_the_filter_noise_replay_without_the_wheel_noise_fits_the_same():
    """C191: adapt's filter noise fits the filter's measurement against the model's rate.

    Neither depends on the pose covariance, so the calibration replays it without the wheel
    noise (no covariance propagated, a third cheaper): the same numbers, bit for bit. And the
    filter records the same intervals either way.
    """
    from skidkin_ros.core.calibration.gyro_fit import fit_filter_noise
    grid, _, config = _drives()
    prefix = f'models.{config.model}.noise.'
    noisy = OdometryConfig.from_flat({**config.values, prefix + 'calibrated': True,
                                      prefix + 'var_x_const': 1e-4,
                                      prefix + 'var_yaw_per_s': 1e-5})
    assert noisy.active_noise is not None and config.active_noise is None
    with_noise = fit_filter_noise(noisy, [grid, grid])
    without = fit_filter_noise(config, [grid, grid])
    assert with_noise == without and with_noise[2] > 100
