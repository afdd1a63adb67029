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
