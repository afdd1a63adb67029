"""Lidar ground truth: kiss-icp odometry of base_link, planar, with guards and a cache.

Recipe (:func:`lidar_ground_truth`): for each lidar frame, check the cloud (C10: empty or tiny
clouds are skipped) and its per-point times (C9), register it with kiss-icp, convert the lidar
pose to base_link with the extrinsic, reduce it to (x, y, yaw), then flag implausible increments
(C12: speed, yaw rate, tilt, dropped frames; C11: disagreement with wheel odometry when given).

What kiss-icp 1.3 expects of the per-point times (read in its C++ ``Preprocessor`` and checked by
experiment, see test/test_lidar_gt.py): it normalises them itself, (t - min) / (max - min), and
moves every point to the sensor pose at the LATEST point with the constant-velocity motion of the
previous frame interval; any unit and any origin work. An EMPTY times array disables deskewing
for that call. Constant or NaN times make the normalisation 0/0 and Sophus aborts the whole
process (exit 134), so such clouds are validated here first and registered without deskew.

Pose stamps: a deskewed pose refers to the latest point of its sweep (``end_ns``). A pose
registered without deskew refers to the middle of the sweep when the point times are known
(``end_ns - spread / 2``) and to ``end_ns`` otherwise.

Frames: kiss-icp's world frame is the lidar frame of the first registered cloud; with
E = T_base_lidar, the base pose in the frame of the first base pose is T_b = E T_l E^-1.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
import hashlib
import io
import json
import logging
import math
import os
from pathlib import Path
from typing import Any, Callable, Iterable, Protocol, Union

import numpy as np

from skidkin_ros.atomic import atomic_write_bytes
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.errors import DataError, ParameterError

__all__ = ['FrameLike', 'GroundTruth', 'IcpConfig', 'STATUS_CODES', 'bag_identity',
           'check_point_times', 'lidar_ground_truth', 'lidar_to_base', 'planar_pose']

_LOG = logging.getLogger(__name__)
CACHE_VERSION = 1

# Frame status codes: ok (valid pose), no_deskew (valid pose, registered without deskew), and
# the reasons a frame gave no pose or an untrusted one.
STATUS_CODES: dict[str, str] = {
    'ok': 'registered with deskew (or deskew off by config)',
    'no_deskew': 'per-point times unusable (C9): registered without deskew',
    'empty': 'no finite point in range: skipped (C10)',
    'tiny': 'fewer points than min_points: skipped (C10)',
    'after_skip': 'first pose after a skipped frame: invalid (C10)',
    'before_skip': 'last pose before a skipped frame: invalid (C10)',
    'gap': 'frame interval above max_gap_factor x the median: a frame was dropped (C12)',
    'speed': 'ICP increment faster than max_speed_m_s (C12)',
    'yaw_rate': 'ICP increment turns faster than max_yaw_rate_rad_s (C12)',
    'tilt': 'roll or pitch beyond max_tilt_rad: ICP left the plane (C11)',
    'wheel_disagreement': 'ICP increment disagrees with wheel odometry beyond tolerance (C11)',
    'non_finite': 'kiss-icp returned a non-finite pose',
}
_VALID_STATUS = ('ok', 'no_deskew')


class FrameLike(Protocol):
    """Any lidar frame: stamp, points (N, 3) in the lidar frame, times, end of sweep."""

    stamp_ns: int
    xyz: np.ndarray
    t_rel_s: np.ndarray | None
    end_ns: int


@dataclass(frozen=True)
class IcpConfig:
    """kiss-icp settings and the plausibility limits of the ground truth.

    Ranges and voxel size in m (voxel_size_m None: max_range_m / 100, kiss-icp's rule); limits
    per frame increment. Wheel disagreement: the ICP and wheel increments over the last
    ``wheel_window_s`` before each pose are compared; flagged when |d_icp - d_wheel| > abs +
    rel |d_wheel| (translation, m) or the same for yaw (rad). Loose on purpose: uncalibrated wheel
    odometry of a skid-steer robot can be far off in yaw (Husky: ~1.9x).
    """

    max_range_m: float = 60.0
    min_range_m: float = 0.5
    voxel_size_m: float | None = None
    deskew: bool = True
    max_threads: int = 0
    min_points: int = 200
    min_time_spread_s: float = 1e-4
    max_time_spread_s: float = 1.0
    max_speed_m_s: float = 3.0
    max_yaw_rate_rad_s: float = 3.0
    max_tilt_rad: float = 0.2
    max_gap_factor: float = 1.5
    wheel_window_s: float = 1.0
    wheel_abs_m: float = 0.1
    wheel_rel: float = 0.5
    wheel_abs_rad: float = 0.1
    wheel_rel_yaw: float = 0.7

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_range_m < self.max_range_m:
            raise ParameterError('IcpConfig: need 0 <= min_range_m < max_range_m (m), got '
                                 f'{self.min_range_m}, {self.max_range_m}')
        if self.voxel_size_m is not None and not self.voxel_size_m > 0.0:
            raise ParameterError(f'IcpConfig.voxel_size_m must be > 0 m, got '
                                 f'{self.voxel_size_m}')
        for name in ('max_speed_m_s', 'max_yaw_rate_rad_s', 'max_tilt_rad', 'min_time_spread_s',
                     'max_time_spread_s'):
            if not getattr(self, name) > 0.0:
                raise ParameterError(f'IcpConfig.{name} must be > 0')
        if self.max_gap_factor <= 1.0:
            raise ParameterError('IcpConfig.max_gap_factor must be > 1 (a multiple of the '
                                 'median frame interval)')
        if self.min_points < 1:
            raise ParameterError('IcpConfig.min_points must be >= 1')

    @property
    def voxel_size(self) -> float:
        return self.voxel_size_m if self.voxel_size_m is not None else self.max_range_m / 100.0

    def kiss_config(self, deskew: bool | None = None) -> Any:
        """Return kiss-icp's KISSConfig built from ``load_config(None)`` with our settings."""
        from kiss_icp.config import load_config

        config = load_config(None)
        config.data.max_range = float(self.max_range_m)
        config.data.min_range = float(self.min_range_m)
        config.data.deskew = self.deskew if deskew is None else deskew
        config.mapping.voxel_size = float(self.voxel_size)
        config.registration.max_num_threads = int(self.max_threads)
        return config


@dataclass(frozen=True)
class GroundTruth:
    """The lidar ground truth of base_link and what happened to every input frame.

    track: planar poses (valid flags set); frame_stamp_ns / frame_status: one entry per input
    frame (status codes in STATUS_CODES); counts: frames per status; from_cache: True when the
    track was read from the cache and no ICP ran.
    """

    track: PoseTrack
    frame_stamp_ns: np.ndarray
    frame_status: tuple[str, ...]
    counts: dict[str, int]
    from_cache: bool = False
    notes: tuple[str, ...] = ()
    config: IcpConfig = field(default_factory=IcpConfig)


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


def lidar_to_base(t_lidar: np.ndarray, extrinsic: np.ndarray) -> np.ndarray:
    """Return the base_link pose E T_lidar E^-1 (E = T_base_lidar), in the first base frame."""
    return extrinsic @ t_lidar @ np.linalg.inv(extrinsic)


def planar_pose(transform: np.ndarray) -> tuple[float, float, float, float]:
    """Return (x, y, yaw, tilt) of a 4x4 pose; tilt is the angle of its z axis from vertical."""
    yaw = math.atan2(transform[1, 0], transform[0, 0])
    tilt = math.acos(max(-1.0, min(1.0, float(transform[2, 2]))))
    return float(transform[0, 3]), float(transform[1, 3]), yaw, tilt


def bag_identity(path: Union[str, os.PathLike]) -> dict[str, Any]:
    """Return what identifies a recording for the cache: resolved path, sizes, mtimes, metadata.

    A bag folder contributes the hash of its metadata.yaml and the size and mtime of each storage
    file; a single file its size and mtime.
    """
    target = Path(path).resolve()
    if not target.exists():
        raise DataError(f'cannot identify recording {target}: it does not exist')
    files = sorted(p for p in target.iterdir() if p.is_file()) if target.is_dir() else [target]
    entries = []
    for item in files:
        stat = item.stat()
        entry = {'name': item.name, 'size': stat.st_size, 'mtime_ns': stat.st_mtime_ns}
        if item.name == 'metadata.yaml':
            entry['sha256'] = hashlib.sha256(item.read_bytes()).hexdigest()
        entries.append(entry)
    return {'path': str(target), 'files': entries}


def _cache_key(source: Any, extrinsic: np.ndarray, config: IcpConfig) -> str:
    payload = {'version': CACHE_VERSION, 'source': source,
               'extrinsic': np.round(np.asarray(extrinsic, dtype=float), 9).tolist(),
               'config': asdict(config)}
    text = json.dumps(payload, sort_keys=True, default=str)
    return hashlib.sha256(text.encode('utf-8')).hexdigest()


def _read_cache(path: Path, key: str, config: IcpConfig) -> GroundTruth | None:
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data['key']) != key:
                return None
            track = PoseTrack(data['t_ns'], data['x'], data['y'], data['yaw'], data['valid'])
            status = tuple(str(s) for s in data['frame_status'])
            frame_stamp = np.asarray(data['frame_stamp_ns'], dtype=np.int64)
    except Exception as err:  # noqa: B902 - any unreadable cache is recomputed, never fatal
        _LOG.warning('ignoring unreadable ground-truth cache %s (%s); recomputing', path, err)
        return None
    counts = {code: status.count(code) for code in STATUS_CODES if code in status}
    return GroundTruth(track, frame_stamp, status, counts, True,
                       (f'ground truth read from cache {path}',), config)


def _write_cache(path: Path, key: str, result: GroundTruth) -> None:
    buffer = io.BytesIO()
    track = result.track
    np.savez(buffer, key=np.array(key), t_ns=track.t_ns, x=track.x, y=track.y, yaw=track.yaw,
             valid=track.valid, frame_status=np.array(result.frame_status, dtype=str),
             frame_stamp_ns=result.frame_stamp_ns)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, buffer.getvalue(), force=True)
    except OSError as err:
        _LOG.warning('could not write the ground-truth cache %s: %s', path, err)


def lidar_ground_truth(frames: Union[Iterable[FrameLike], Callable[[], Iterable[FrameLike]]],
                       extrinsic: np.ndarray, config: IcpConfig | None = None, *,
                       wheel_odometry: PoseTrack | None = None, progress: bool = False,
                       total: int | None = None, cache_dir: Union[str, os.PathLike, None] = None,
                       source_id: Any = None) -> GroundTruth:
    """Run kiss-icp over lidar frames and return the planar ground truth of base_link.

    frames: an iterable of frames (or a callable returning one, only called on a cache miss);
    extrinsic: T_base_lidar (4x4); wheel_odometry: optional wheel-odometry track of base_link
    to flag ICP increments that disagree with it (C11); cache_dir + source_id (e.g.
    ``{'bag': bag_identity(path), 'topic': topic}``): cache the result keyed by the source,
    the extrinsic and the config; a corrupt or stale cache is recomputed.
    """
    config = config or IcpConfig()
    extrinsic = np.asarray(extrinsic, dtype=float)
    if extrinsic.shape != (4, 4) or not np.all(np.isfinite(extrinsic)):
        raise ParameterError('extrinsic must be a finite 4x4 T_base_lidar (m, rotation matrix)')
    cache_path = None
    if cache_dir is not None and source_id is not None:
        key = _cache_key(source_id, extrinsic, config)
        cache_path = Path(cache_dir) / f'lidar_gt_{key[:24]}.npz'
        cached = _read_cache(cache_path, key, config)
        if cached is not None:
            _LOG.info('lidar ground truth read from cache %s', cache_path)
            return cached
    source = frames() if callable(frames) else frames
    result = _register_all(source, extrinsic, config, wheel_odometry, progress, total)
    if cache_path is not None:
        _write_cache(cache_path, key, result)
    return result


def _register_all(frames: Iterable[FrameLike], extrinsic: np.ndarray, config: IcpConfig,
                  wheel_odometry: PoseTrack | None, progress: bool,
                  total: int | None) -> GroundTruth:
    from kiss_icp.kiss_icp import KissICP

    odometry = KissICP(config.kiss_config())
    iterator: Iterable[FrameLike] = frames
    if progress:
        from tqdm import tqdm
        iterator = tqdm(frames, total=total, unit='scan', desc='kiss-icp')
    no_times = np.zeros(0)
    status: list[str] = []
    frame_stamps: list[int] = []
    pose_rows: list[tuple[int, float, float, float, float]] = []
    pose_frame: list[int] = []
    notes: list[str] = []
    for index, frame in enumerate(iterator):
        frame_stamps.append(int(frame.end_ns))
        xyz = np.asarray(frame.xyz, dtype=np.float64).reshape(-1, 3)
        finite = np.all(np.isfinite(xyz), axis=1)
        ranges = np.linalg.norm(xyz, axis=1)
        usable = finite & (ranges > config.min_range_m) & (ranges < config.max_range_m)
        n_usable = int(np.count_nonzero(usable))
        if n_usable == 0 or n_usable < config.min_points:
            status.append('empty' if n_usable == 0 else 'tiny')
            continue
        times = frame.t_rel_s
        times_ok, why = check_point_times(times, xyz.shape[0], config)
        if times_ok and not np.all(finite):
            times = np.asarray(times, dtype=float)[finite]
        points = np.ascontiguousarray(xyz[finite])
        code = 'ok'
        t_pose = int(frame.end_ns)
        if not times_ok:
            if config.deskew:
                _LOG.debug('frame %d at %d ns: %s; registered without deskew', index,
                           frame.end_ns, why)
            code = 'no_deskew' if config.deskew else 'ok'
            stamps = no_times
        else:
            spread_ns = int(round(float(np.ptp(times)) * 1e9))
            if config.deskew:
                stamps = np.ascontiguousarray(times, dtype=np.float64)
            else:
                stamps = no_times
                t_pose = int(frame.end_ns) - spread_ns // 2
        odometry.register_frame(points, stamps)
        t_base = lidar_to_base(odometry.last_pose, extrinsic)
        x, y, yaw, tilt = planar_pose(t_base)
        if not all(math.isfinite(v) for v in (x, y, yaw)):
            status.append('non_finite')
            continue
        status.append(code)
        pose_rows.append((t_pose, x, y, yaw, tilt))
        pose_frame.append(index)
    frame_stamp_ns = np.array(frame_stamps, dtype=np.int64)
    track = _flag_track(pose_rows, pose_frame, status, frame_stamp_ns, config, wheel_odometry)
    counts = {code: status.count(code) for code in STATUS_CODES if code in status}
    skipped = counts.get('empty', 0) + counts.get('tiny', 0)
    if skipped:
        notes.append(f'{skipped} lidar frame(s) skipped: empty or fewer than '
                     f'{config.min_points} points (C10)')
    if counts.get('no_deskew'):
        notes.append(f'{counts["no_deskew"]} frame(s) registered without deskew: per-point '
                     'times missing, constant or NaN (C9)')
    flagged = sum(counts.get(c, 0) for c in ('gap', 'speed', 'yaw_rate', 'tilt',
                                             'wheel_disagreement', 'after_skip', 'before_skip'))
    if flagged:
        notes.append(f'{flagged} ground-truth pose(s) flagged invalid (C11/C12)')
    for note in notes:
        _LOG.info(note)
    return GroundTruth(track, frame_stamp_ns, tuple(status), counts, False, tuple(notes),
                       config)


def _flag_track(rows: list, pose_frame: list[int], status: list[str],
                frame_stamp_ns: np.ndarray, config: IcpConfig,
                wheel_odometry: PoseTrack | None) -> PoseTrack:
    """Build the track and flag implausible poses, writing the reason into ``status``."""
    if not rows:
        empty = np.zeros(0)
        return PoseTrack(np.zeros(0, dtype=np.int64), empty, empty, empty, np.zeros(0, bool))
    data = np.array([row[1:] for row in rows], dtype=float)
    t_ns = np.array([row[0] for row in rows], dtype=np.int64)
    order = np.argsort(t_ns, kind='stable')
    if np.any(order != np.arange(order.size)):
        _LOG.warning('lidar frames out of time order: sorted %d poses', order.size)
        data, t_ns = data[order], t_ns[order]
        pose_frame = [pose_frame[i] for i in order]
    x, y, tilt = data[:, 0], data[:, 1], data[:, 3]
    yaw = np.unwrap(data[:, 2])
    reasons = [''] * len(rows)

    def flag(i: int, code: str) -> None:
        if not reasons[i]:
            reasons[i] = code

    for i in np.flatnonzero(tilt > config.max_tilt_rad):
        flag(int(i), 'tilt')
    frame_dt = np.diff(frame_stamp_ns)
    nominal_ns = float(np.median(frame_dt)) if frame_dt.size else 0.0
    skipped = {i for i, code in enumerate(status) if code in ('empty', 'tiny')}
    for j in range(1, len(rows)):
        dt_s = (t_ns[j] - t_ns[j - 1]) * 1e-9
        frames_between = set(range(pose_frame[j - 1] + 1, pose_frame[j]))
        if frames_between & skipped:
            flag(j, 'after_skip')
            flag(j - 1, 'before_skip')
            continue
        if dt_s <= 0.0:
            flag(j, 'gap')
            continue
        if nominal_ns > 0 and (t_ns[j] - t_ns[j - 1]) > config.max_gap_factor * nominal_ns:
            flag(j, 'gap')
        step = math.hypot(x[j] - x[j - 1], y[j] - y[j - 1])
        turn = abs(yaw[j] - yaw[j - 1])
        if step / dt_s > config.max_speed_m_s:
            flag(j, 'speed')
        if turn / dt_s > config.max_yaw_rate_rad_s:
            flag(j, 'yaw_rate')
        if wheel_odometry is not None:
            k = int(np.searchsorted(t_ns, t_ns[j] - int(config.wheel_window_s * 1e9)))
            k = min(k, j - 1)
            if _disagrees(wheel_odometry, t_ns[k], t_ns[j], (x[k], y[k], yaw[k]),
                          (x[j], y[j], yaw[j]), config):
                flag(j, 'wheel_disagreement')
    for i, reason in enumerate(reasons):
        if reason:
            status[pose_frame[i]] = reason
    valid = np.array([not reason for reason in reasons])
    return PoseTrack(t_ns, x, y, yaw, valid)


def _body_increment(a: tuple, b: tuple) -> tuple[float, float, float]:
    """Return the increment from pose a to pose b in a's frame: (dx, dy, dyaw)."""
    cos_a, sin_a = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return cos_a * dx + sin_a * dy, -sin_a * dx + cos_a * dy, b[2] - a[2]


def _disagrees(wheel: PoseTrack, t0_ns: int, t1_ns: int, icp0: tuple, icp1: tuple,
               config: IcpConfig) -> bool:
    if len(wheel) < 2 or t0_ns < wheel.t_ns[0] or t1_ns > wheel.t_ns[-1]:
        return False
    w0, w1 = wheel.interpolate([t0_ns, t1_ns])
    wdx, wdy, wdyaw = _body_increment(tuple(w0), tuple(w1))
    idx, idy, idyaw = _body_increment(icp0, icp1)
    wheel_step = math.hypot(wdx, wdy)
    if math.hypot(idx - wdx, idy - wdy) > config.wheel_abs_m + config.wheel_rel * wheel_step:
        return True
    return abs(idyaw - wdyaw) > config.wheel_abs_rad + config.wheel_rel_yaw * abs(wdyaw)
