"""Registering lidar frames with kiss-icp: input checks, the motion model in time, the loop.

One job: :func:`register_frames` and what it needs (the per-point time check, kiss-icp with a
constant velocity in time); :mod:`skidkin_ros.adapters.lidar_gt` describes the loop's changes
to kiss-icp and what kiss-icp expects of the point times.
"""

from __future__ import annotations

import logging
import math
from typing import Any, Callable, Iterable

import numpy as np

from skidkin_ros.adapters.icp_config import IcpConfig
from skidkin_ros.adapters.lidar_frames import FrameGrid, FrameLike, Registration
from skidkin_ros.adapters.lidar_quality import _world, registration_quality
from skidkin_ros.core.rigid import se3_exp_scaled, se3_log
from skidkin_ros.core.timeunits import s_to_ns

__all__ = ['check_point_times', 'register_frames']

# The lidar ground truth logs under one name, that of lidar_gt, wherever the code lives.
_LOG = logging.getLogger('skidkin_ros.adapters.lidar_gt')
# The quality measure's tree of the previous map points, built once per frame and queried with
# 400 points: unbalanced and not compacted builds in 2/3 of the time, and its nearest distances
# are the same to the last bit (the same points, the same distance arithmetic).
_TREE = {'balanced_tree': False, 'compact_nodes': False}


def check_point_times(t_rel_s: np.ndarray | None, n_points: int,
                      config: IcpConfig) -> tuple[bool, str]:
    """Tell whether per-point times can be handed to kiss-icp for deskewing, and why not (C9)."""
    if t_rel_s is None:
        return False, 'no per-point times'
    times = np.asarray(t_rel_s, dtype=float).ravel()
    if times.size != n_points:
        return False, f'{times.size} times for {n_points} points'
    if times.size == 0:
        return False, 'no points'
    if not np.all(np.isfinite(times)):
        return False, f'{int(np.count_nonzero(~np.isfinite(times)))} non-finite times'
    spread = float(times.max() - times.min())
    if spread < config.min_time_spread_s:
        return False, f'times (nearly) constant: spread {spread:.3g} s'
    if spread > config.max_time_spread_s:
        return False, f'time spread {spread:.3g} s longer than a sweep (unit?)'
    return True, ''


class _Odometry:
    """kiss-icp's KissICP with a constant-velocity model in time and the map points kept."""

    def __init__(self, config: IcpConfig) -> None:
        from kiss_icp.kiss_icp import KissICP

        self._kiss = KissICP(config.kiss_config())
        self._last_dt_ns = 0

    @property
    def last_pose(self) -> np.ndarray:
        return self._kiss.last_pose

    def register(self, points: np.ndarray, times: np.ndarray, dt_ns: int,
                 spread_ns: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Register one cloud ``dt_ns`` after the previous one; return (source, map points).

        The map points are None when kiss-icp's pose is not finite (nothing was updated).
        """
        kiss = self._kiss
        delta = kiss.last_delta
        if self._last_dt_ns > 0 and dt_ns > 0:
            # one logarithm for both: the guess and the sweep are the same motion, scaled
            twist = se3_log(delta)
            guess_delta = se3_exp_scaled(*twist, dt_ns / self._last_dt_ns)
            sweep_delta = se3_exp_scaled(*twist, min(spread_ns, dt_ns) / self._last_dt_ns)
        else:
            guess_delta = sweep_delta = delta
        frame = kiss.preprocessor.preprocess(points, times, sweep_delta)
        source, frame_downsample = kiss.voxelize(frame)
        sigma = kiss.adaptive_threshold.get_threshold()
        initial_guess = kiss.last_pose @ guess_delta
        new_pose = kiss.registration.align_points_to_map(
            points=source, voxel_map=kiss.local_map, initial_guess=initial_guess,
            max_correspondance_distance=3 * sigma, kernel=sigma)
        if not np.all(np.isfinite(new_pose)):
            # kept out of kiss-icp's map and motion model: Sophus aborts the process on it, and
            # the next frame registers from the last good pose
            return source, None
        kiss.adaptive_threshold.update_model_deviation(np.linalg.inv(initial_guess) @ new_pose)
        kiss.local_map.update(frame_downsample, new_pose)
        kiss.last_delta = np.linalg.inv(kiss.last_pose) @ new_pose
        kiss.last_pose = new_pose
        self._last_dt_ns = dt_ns if dt_ns > 0 else self._last_dt_ns
        return source, frame_downsample


def _prepare(frame: FrameLike, index: int, config: IcpConfig
             ) -> tuple[str, np.ndarray | None, np.ndarray, int, int]:
    """Check one cloud; return (code, points, times for kiss-icp, pose stamp, sweep ns)."""
    xyz = np.asarray(frame.xyz, dtype=np.float64).reshape(-1, 3)
    # column by column: numpy's reductions over a row of 3 cost more than the arithmetic
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    finite = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
    with np.errstate(over='ignore', invalid='ignore'):  # beyond 1e154 m: an infinite range
        ranges = np.sqrt(x * x + y * y + z * z)
    usable = finite & (ranges > config.min_range_m) & (ranges < config.max_range_m)
    n_usable = int(np.count_nonzero(usable))
    end = int(frame.end_ns)
    if n_usable == 0 or n_usable < config.min_points:
        return ('empty' if n_usable == 0 else 'tiny'), None, np.zeros(0), end, 0
    times = frame.t_rel_s
    times_ok, why = check_point_times(times, xyz.shape[0], config)
    all_finite = bool(np.all(finite))
    if times_ok and not all_finite:
        times = np.asarray(times, dtype=float)[finite]
    points = np.ascontiguousarray(xyz if all_finite else xyz[finite])
    if not times_ok:
        if config.deskew:
            _LOG.debug('frame %d at %d ns: %s; registered without deskew', index, end, why)
        return ('no_deskew' if config.deskew else 'ok'), points, np.zeros(0), end, 0
    spread_ns = s_to_ns(float(np.ptp(times)))
    if not config.deskew:
        return 'ok', points, np.zeros(0), end - spread_ns // 2, spread_ns
    return 'ok', points, np.ascontiguousarray(times, dtype=np.float64), end, spread_ns


def register_frames(frames: Iterable[FrameLike], config: IcpConfig, *,
                    grid: FrameGrid | None = None,
                    on_frame: Callable[[int], None] | None = None) -> Registration:
    """Register lidar frames with kiss-icp; return one entry per frame (see Registration).

    ``grid``: which scans to register when ``config.stride`` > 1 (default: cells on the
    interval of the first two frames); ``on_frame(n)`` is called after each frame with the
    number of frames read so far.
    """
    from scipy.spatial import cKDTree

    odometry: _Odometry | None = None
    end_ns: list[int] = []
    receive_ns: list[int] = []
    status: list[str] = []
    pose_t: list[int] = []
    poses: list[np.ndarray] = []
    quality: list[tuple[float, float, float]] = []
    nan_pose = np.full((4, 4), np.nan)
    nan_quality = (math.nan, math.nan, math.nan)
    reference: Any = None
    last_end: int | None = None
    last_cell: int | None = None
    for index, frame in enumerate(frames):
        end = int(frame.end_ns)
        end_ns.append(end)
        receive_ns.append(int(getattr(frame, 'receive_ns', end)))
        code, pose, stamp, measured = 'stride', nan_pose, -1, nan_quality
        if config.stride > 1 and grid is None and index == 1:
            grid = FrameGrid.for_frames(end_ns[0], end - end_ns[0], config.stride)
            last_cell = grid.cell(last_end) if last_end is not None else None
        cell = grid.cell(end) if (config.stride > 1 and grid is not None) else None
        if cell is None or cell != last_cell:
            code, points, times, stamp, spread_ns = _prepare(frame, index, config)
            if points is not None:
                if odometry is None:
                    config = config.with_voxel_for(points)
                    odometry = _Odometry(config)
                dt_ns = end - last_end if last_end is not None else 0
                source, map_points = odometry.register(points, times, dt_ns, spread_ns)
                pose = odometry.last_pose.copy()
                if map_points is None or not np.all(np.isfinite(pose)):
                    code, pose, stamp = 'non_finite', nan_pose, -1
                else:
                    if reference is not None:
                        measured = registration_quality(source, pose, reference,
                                                        config.voxel_size, config.quality_points)
                    reference = cKDTree(_world(map_points, pose), **_TREE)
                    last_end, last_cell = end, cell
            else:
                pose, stamp = nan_pose, -1
        status.append(code)
        pose_t.append(stamp)
        poses.append(pose)
        quality.append(measured)
        if on_frame is not None:
            on_frame(index + 1)
    return Registration(np.array(end_ns, dtype=np.int64), tuple(status),
                        np.array(pose_t, dtype=np.int64),
                        np.array(poses, dtype=float).reshape(-1, 4, 4),
                        *(np.array([q[i] for q in quality], dtype=float) for i in range(3)),
                        receive_ns=np.array(receive_ns, dtype=np.int64),
                        voxel_size_m=config.voxel_size_m)
