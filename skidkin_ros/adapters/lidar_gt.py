"""Lidar ground truth: kiss-icp odometry of base_link, planar, with the quality of every frame.

Recipe (:func:`lidar_ground_truth`): register the lidar frames with kiss-icp
(:func:`register_frames`), measure each registration's own quality, convert the lidar poses to
base_link with the extrinsic, reduce them to (x, y, yaw), then let
:mod:`skidkin_ros.adapters.lidar_guard` flag what cannot be trusted. Long recordings are cut
into chunks registered independently (:mod:`skidkin_ros.adapters.lidar_chunks`); what the
registration of one chunk returns (:class:`Registration`) is what the cache stores, so the flags
are recomputed on every run from the current wheels, IMU and limits.

The registration loop is kiss-icp's ``KissICP.register_frame`` with two changes, both about
time: the motion model is a constant velocity *in time* (kiss-icp assumes one frame interval
per registered frame), so registering every k-th scan (``IcpConfig.stride``) or a frame after a
dropped one gets the right initial guess and deskews with the motion of one sweep, not of the
whole interval; and the points that go into the map are kept to measure the next frame.

ICP quality, measured per frame against the previous registered frame (a k-d tree of its
map-resolution points in the world frame; up to ``quality_points`` source points sampled):

* ``inlier_fraction``: share of the sampled points with a neighbour within one voxel;
* ``residual_m``: median distance of those points to their neighbour (kiss-icp's own
  point-to-point error);
* ``degeneracy``: how well the scan's structure above the ground surrounds the sensor (see
  :func:`registration_quality`): 0 when the planar position is unobservable (an open field, a
  straight corridor).

What kiss-icp 1.3 expects of the per-point times (read in its C++ ``Preprocessor`` and checked by
experiment, see test/test_lidar_gt.py): it normalises them itself, (t - min) / (max - min), and
moves every point to the sensor pose at the LATEST point with the motion it is given; any unit
and any origin work. An EMPTY times array disables deskewing for that call. Constant or NaN
times make the normalisation 0/0 and Sophus aborts the whole process (exit 134), so such clouds
are validated here first and registered without deskew.

Pose stamps: a deskewed pose refers to the latest point of its sweep (``end_ns``). A pose
registered without deskew refers to the middle of the sweep when the point times are known
(``end_ns - spread / 2``) and to ``end_ns`` otherwise.

Frames: kiss-icp's world frame is the lidar frame of the first registered cloud; with
E = T_base_lidar, the base pose in the frame of the first base pose is T_b = E T_l E^-1.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
import logging
import math
from typing import Any, Callable, Iterable, Protocol

import numpy as np

from skidkin_ros.core.drive import ImuSamples, PoseTrack, WheelSamples
from skidkin_ros.core.rigid import planar_poses, se3_power
from skidkin_ros.core.timeunits import s_to_ns
from skidkin_ros.errors import ParameterError

__all__ = ['auto_voxel_size', 'BaseTrack', 'FrameGrid', 'FrameLike', 'GroundTruth',
           'guarded_truth', 'IcpConfig', 'Registration', 'REGISTRATION_CODES',
           'check_point_times', 'lidar_ground_truth', 'register_frames', 'registration_quality',
           'track_from_registration']

_LOG = logging.getLogger(__name__)

# What the registration did with each frame; the guard adds its own codes (lidar_guard).
REGISTRATION_CODES: dict[str, str] = {
    'ok': 'registered with deskew (or deskew off by config)',
    'no_deskew': 'per-point times unusable (C9): registered without deskew',
    'stride': 'not registered: only every IcpConfig.stride-th scan is',
    'empty': 'no finite point in range: skipped (C10)',
    'tiny': 'fewer points than min_points: skipped (C10)',
    'non_finite': 'kiss-icp returned a non-finite pose',
}
REGISTERED = ('ok', 'no_deskew')
# Points this far above the lowest tenth of a scan count as structure (not ground).
_GROUND_CLEARANCE_M = 0.3


class FrameLike(Protocol):
    """Any lidar frame: stamp, points (N, 3) in the lidar frame, times, end of sweep."""

    stamp_ns: int
    xyz: np.ndarray
    t_rel_s: np.ndarray | None
    end_ns: int


@dataclass(frozen=True)
class IcpConfig:
    """kiss-icp settings and the checks of its input: everything a registration depends on.

    Ranges and voxel size in m (voxel_size_m None: from the data, :func:`auto_voxel_size`;
    kiss-icp's own rule, max_range / 100, ties it to the sensor instead of the scene);
    ``max_points_per_voxel``, ``max_iterations`` and ``convergence`` are kiss-icp's mapping and
    registration settings; ``stride``: register one scan in ``stride`` (the others get status
    'stride'); ``max_threads``: kiss-icp's threads per registration (1: the result does not
    depend on the machine or on how many run at once; kiss-icp 1.3's threaded reduction changes
    the last bits of the poses, docs/ground-truth.md; 0: every core). ``quality_points``:
    source points sampled per frame to measure the registration's quality.
    The defaults come from the speed/accuracy table of bench/icp_settings.py (docs/benchmarks.md).
    """

    max_range_m: float = 100.0
    min_range_m: float = 0.5
    voxel_size_m: float | None = None
    max_points_per_voxel: int = 20
    max_iterations: int = 500
    convergence: float = 1e-3
    stride: int = 1
    deskew: bool = True
    max_threads: int = 1
    min_points: int = 200
    min_time_spread_s: float = 1e-4
    max_time_spread_s: float = 1.0
    quality_points: int = 400

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_range_m < self.max_range_m:
            raise ParameterError('IcpConfig: need 0 <= min_range_m < max_range_m (m), got '
                                 f'{self.min_range_m}, {self.max_range_m}')
        if self.voxel_size_m is not None and not self.voxel_size_m > 0.0:
            raise ParameterError(f'IcpConfig.voxel_size_m must be > 0 m, got '
                                 f'{self.voxel_size_m}')
        for name in ('min_time_spread_s', 'max_time_spread_s', 'convergence'):
            if not getattr(self, name) > 0.0:
                raise ParameterError(f'IcpConfig.{name} must be > 0, got {getattr(self, name)}')
        for name, low in (('min_points', 1), ('max_points_per_voxel', 1),
                          ('max_iterations', 1), ('stride', 1), ('max_threads', 0),
                          ('quality_points', 0)):
            value = getattr(self, name)
            if not isinstance(value, int) or value < low:
                raise ParameterError(f'IcpConfig.{name} must be a whole number >= {low}, got '
                                     f'{value!r}')

    @property
    def voxel_size(self) -> float:
        if self.voxel_size_m is None:
            raise ParameterError('IcpConfig.voxel_size_m is not resolved yet: use '
                                 'with_voxel_for(first cloud) first')
        return self.voxel_size_m

    def with_voxel_for(self, xyz: np.ndarray) -> 'IcpConfig':
        """Return this config with its voxel size set from a cloud when it is automatic."""
        if self.voxel_size_m is not None:
            return self
        return replace(self, voxel_size_m=auto_voxel_size(xyz, self))

    def kiss_config(self) -> Any:
        """Return kiss-icp's KISSConfig built from ``load_config(None)`` with our settings."""
        from kiss_icp.config import load_config

        config = load_config(None)
        config.data.max_range = float(self.max_range_m)
        config.data.min_range = float(self.min_range_m)
        config.data.deskew = self.deskew
        config.mapping.voxel_size = float(self.voxel_size)
        config.mapping.max_points_per_voxel = int(self.max_points_per_voxel)
        config.registration.max_num_iterations = int(self.max_iterations)
        config.registration.convergence_criterion = float(self.convergence)
        config.registration.max_num_threads = int(self.max_threads)
        return config

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


# The automatic voxel: this many times the median spacing of neighbouring points of a scan.
VOXEL_PER_SPACING = 6.0
_VOXEL_RANGE_M = (0.2, 3.0)


def auto_voxel_size(xyz: np.ndarray, config: IcpConfig) -> float:
    """Return a voxel size (m) for kiss-icp from one cloud: 6 x its median point spacing.

    kiss-icp ties the voxel to the sensor's range (max_range / 100); what registers well is a
    voxel that holds a few points of the scan at hand, so it grows with how sparse the scan is:
    0.55 m for a 16-ring lidar at 0.5 deg in a courtyard (median spacing 9 cm), 1.4 m for the
    same lidar at 1 deg among trees (23 cm). The factor comes from the speed/accuracy table of
    bench/icp_settings.py. Rounded to 5 cm, within 0.2-3 m.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(xyz, dtype=float).reshape(-1, 3)
    points = points[np.all(np.isfinite(points), axis=1)]
    ranges = np.linalg.norm(points, axis=1)
    points = points[(ranges > config.min_range_m) & (ranges < config.max_range_m)]
    if points.shape[0] < 10:
        return 1.0
    spacing, _ = cKDTree(points).query(points, k=2)
    voxel = VOXEL_PER_SPACING * float(np.median(spacing[:, 1]))
    return float(np.clip(round(voxel / 0.05) * 0.05, *_VOXEL_RANGE_M))


@dataclass(frozen=True)
class FrameGrid:
    """Which scans to register when ``stride`` > 1: the first one in each cell of a time grid.

    Cells of ``cell_ns`` (stride x the nominal frame period) start at ``origin_ns``. The grid
    is fixed in absolute time, so chunks of one recording register the same scans.
    """

    origin_ns: int
    cell_ns: int

    @classmethod
    def for_frames(cls, first_end_ns: int, period_ns: int, stride: int) -> 'FrameGrid':
        """Return the grid whose cells are centred on the frames (half a period of jitter ok)."""
        return cls(int(first_end_ns) - int(period_ns) // 2, int(period_ns) * int(stride))

    def cell(self, end_ns: int) -> int:
        return (int(end_ns) - self.origin_ns) // self.cell_ns


@dataclass
class Registration:
    """What registering a sequence of frames gave, one entry per input frame.

    ``status`` (REGISTRATION_CODES); ``pose_t_ns`` the pose stamp (-1 without a pose);
    ``lidar_pose`` (F, 4, 4) in the lidar frame of the first registered cloud (NaN without a
    pose); the quality of each registration (NaN where not measured: no pose, or the first
    frame of the sequence); ``notes`` about the input (times unusable, ...).
    """

    end_ns: np.ndarray
    status: tuple[str, ...]
    pose_t_ns: np.ndarray
    lidar_pose: np.ndarray
    inlier_fraction: np.ndarray
    residual_m: np.ndarray
    degeneracy: np.ndarray
    receive_ns: np.ndarray | None = None
    voxel_size_m: float | None = None

    ARRAYS = ('end_ns', 'pose_t_ns', 'lidar_pose', 'inlier_fraction', 'residual_m',
              'degeneracy')

    def __len__(self) -> int:
        return int(self.end_ns.size)

    @property
    def registered(self) -> np.ndarray:
        return np.array([code in REGISTERED for code in self.status], dtype=bool)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Return plain arrays (for np.savez and for sending between processes)."""
        out = {name: getattr(self, name) for name in self.ARRAYS}
        out['status'] = np.array(self.status, dtype=str)
        if self.receive_ns is not None:
            out['receive_ns'] = self.receive_ns
        if self.voxel_size_m is not None:
            out['voxel_size_m'] = np.array(self.voxel_size_m)
        return out

    @classmethod
    def from_arrays(cls, arrays: Any) -> 'Registration':
        """Rebuild from :meth:`to_arrays` output (or an open npz)."""
        receive = arrays['receive_ns'] if 'receive_ns' in arrays else None
        voxel = float(arrays['voxel_size_m']) if 'voxel_size_m' in arrays else None
        return cls(np.asarray(arrays['end_ns'], dtype=np.int64),
                   tuple(str(s) for s in arrays['status']),
                   np.asarray(arrays['pose_t_ns'], dtype=np.int64),
                   np.asarray(arrays['lidar_pose'], dtype=float).reshape(-1, 4, 4),
                   *(np.asarray(arrays[name], dtype=float)
                     for name in ('inlier_fraction', 'residual_m', 'degeneracy')),
                   receive_ns=None if receive is None else np.asarray(receive, dtype=np.int64),
                   voxel_size_m=voxel)


@dataclass(frozen=True)
class GroundTruth:
    """The lidar ground truth of base_link and what happened to every input frame.

    track: planar poses (valid flags set); frame_stamp_ns / frame_status: one entry per input
    frame (REGISTRATION_CODES and the guard's codes); counts: frames per status; from_cache:
    True when every chunk's registration was read from the cache (no ICP ran); excluded: the
    guard's account of what it excluded and why (see lidar_guard).
    """

    track: PoseTrack
    frame_stamp_ns: np.ndarray
    frame_status: tuple[str, ...]
    counts: dict[str, int]
    from_cache: bool = False
    notes: tuple[str, ...] = ()
    config: IcpConfig = field(default_factory=IcpConfig)
    excluded: dict[str, Any] = field(default_factory=dict)


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
                 spread_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """Register one cloud ``dt_ns`` after the previous one; return (source, map points)."""
        kiss = self._kiss
        delta = kiss.last_delta
        if self._last_dt_ns > 0 and dt_ns > 0:
            guess_delta = se3_power(delta, dt_ns / self._last_dt_ns)
            sweep_delta = se3_power(delta, min(spread_ns, dt_ns) / self._last_dt_ns)
        else:
            guess_delta = sweep_delta = delta
        frame = kiss.preprocessor.preprocess(points, times, sweep_delta)
        source, frame_downsample = kiss.voxelize(frame)
        sigma = kiss.adaptive_threshold.get_threshold()
        initial_guess = kiss.last_pose @ guess_delta
        new_pose = kiss.registration.align_points_to_map(
            points=source, voxel_map=kiss.local_map, initial_guess=initial_guess,
            max_correspondance_distance=3 * sigma, kernel=sigma)
        kiss.adaptive_threshold.update_model_deviation(np.linalg.inv(initial_guess) @ new_pose)
        kiss.local_map.update(frame_downsample, new_pose)
        kiss.last_delta = np.linalg.inv(kiss.last_pose) @ new_pose
        kiss.last_pose = new_pose
        self._last_dt_ns = dt_ns if dt_ns > 0 else self._last_dt_ns
        return source, frame_downsample


def _world(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    return points @ pose[:3, :3].T + pose[:3, 3]


def registration_quality(source: np.ndarray, pose: np.ndarray, reference: Any,
                         voxel_m: float, n_sample: int) -> tuple[float, float, float]:
    """Return (inlier fraction, median residual m, degeneracy) of one registered frame.

    ``source``: the points kiss-icp registered (deskewed, sensor frame); ``reference``: a
    cKDTree of the previous frame's map points in the world frame. A sampled point is an inlier
    when the reference has a point within one voxel; the residual is the median distance of the
    inliers (what kiss-icp's point-to-point ICP minimises). Degeneracy: the smallest eigenvalue
    of the mean of u u^T over the sampled points, u the horizontal unit direction of a point
    standing above the ground (0.3 m over the lowest tenth of the points) and 0 for a ground
    point: 0 when nothing constrains the planar position (an open field, only the ground) or
    when all structure lies along one line (a corridor), up to 0.5 for structure all around.
    """
    if n_sample <= 0 or source.shape[0] == 0:
        return math.nan, math.nan, math.nan
    step = max(1, source.shape[0] // n_sample)
    local = source[::step][:n_sample]
    dist, _ = reference.query(_world(local, pose), k=1, distance_upper_bound=voxel_m)
    near = np.isfinite(dist)
    inlier_fraction = float(np.count_nonzero(near)) / local.shape[0]
    residual = float(np.median(dist[near])) if np.any(near) else math.nan
    structure = local[local[:, 2] > np.percentile(local[:, 2], 10) + _GROUND_CLEARANCE_M]
    horizontal = np.hypot(structure[:, 0], structure[:, 1])
    structure = structure[horizontal > 1e-6]
    if structure.shape[0] == 0:
        return inlier_fraction, residual, 0.0
    u = structure[:, :2] / np.hypot(structure[:, 0], structure[:, 1])[:, None]
    degeneracy = float(np.linalg.eigvalsh(u.T @ u / local.shape[0])[0])
    return inlier_fraction, residual, degeneracy


def _prepare(frame: FrameLike, index: int, config: IcpConfig
             ) -> tuple[str, np.ndarray | None, np.ndarray, int, int]:
    """Check one cloud; return (code, points, times for kiss-icp, pose stamp, sweep ns)."""
    xyz = np.asarray(frame.xyz, dtype=np.float64).reshape(-1, 3)
    finite = np.all(np.isfinite(xyz), axis=1)
    ranges = np.linalg.norm(xyz, axis=1)
    usable = finite & (ranges > config.min_range_m) & (ranges < config.max_range_m)
    n_usable = int(np.count_nonzero(usable))
    end = int(frame.end_ns)
    if n_usable == 0 or n_usable < config.min_points:
        return ('empty' if n_usable == 0 else 'tiny'), None, np.zeros(0), end, 0
    times = frame.t_rel_s
    times_ok, why = check_point_times(times, xyz.shape[0], config)
    if times_ok and not np.all(finite):
        times = np.asarray(times, dtype=float)[finite]
    points = np.ascontiguousarray(xyz[finite])
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
                if not np.all(np.isfinite(pose)):
                    code, pose, stamp = 'non_finite', nan_pose, -1
                else:
                    if reference is not None:
                        measured = registration_quality(source, pose, reference,
                                                        config.voxel_size, config.quality_points)
                    reference = cKDTree(_world(map_points, pose))
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


@dataclass(frozen=True)
class BaseTrack:
    """Planar base_link poses from a registration, before the guard: one row per pose."""

    t_ns: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    tilt: np.ndarray
    quality: np.ndarray
    pose_frame: np.ndarray


def track_from_registration(registration: Registration, extrinsic: np.ndarray) -> BaseTrack:
    """Return the registered poses as planar base_link poses, sorted by time, yaw unwrapped."""
    rows = np.flatnonzero(registration.registered)
    data = planar_poses(registration.lidar_pose[rows], extrinsic)
    t_ns = registration.pose_t_ns[rows]
    order = np.argsort(t_ns, kind='stable')
    if np.any(order != np.arange(order.size)):
        _LOG.warning('lidar frames out of time order: sorted %d poses', order.size)
    rows, data, t_ns = rows[order], data[order], t_ns[order]
    quality = np.stack([registration.inlier_fraction[rows], registration.residual_m[rows],
                        registration.degeneracy[rows]], axis=-1).reshape(-1, 3)
    return BaseTrack(t_ns, data[:, 0], data[:, 1], np.unwrap(data[:, 2]), data[:, 3], quality,
                     rows)


def guarded_truth(registration: Registration, extrinsic: np.ndarray, config: IcpConfig,
                  limits: Any = None, *, wheels: WheelSamples | None = None,
                  imu: ImuSamples | None = None, seams: Iterable[int] = (),
                  from_cache: bool = False, notes: Iterable[str] = ()) -> GroundTruth:
    """Return the ground truth of a registration: base_link track, guard flags, notes.

    ``seams``: input-frame indices whose pose starts a chunk after a seam that failed its test.
    """
    from skidkin_ros.adapters.lidar_guard import flag_poses, GuardLimits

    limits = limits or GuardLimits()
    extrinsic = np.asarray(extrinsic, dtype=float)
    if extrinsic.shape != (4, 4) or not np.all(np.isfinite(extrinsic)):
        raise ParameterError('extrinsic must be a finite 4x4 T_base_lidar (m, rotation matrix)')
    base = track_from_registration(registration, extrinsic)
    seam_frames = {int(i) for i in seams}
    seam_poses = [j for j, frame in enumerate(base.pose_frame) if int(frame) in seam_frames]
    reasons, exclusions = flag_poses(base.t_ns, base.x, base.y, base.yaw, base.tilt,
                                     base.quality, base.pose_frame, registration.status,
                                     limits, wheels=wheels, imu=imu, seams=seam_poses)
    status = list(registration.status)
    for frame, reason in zip(base.pose_frame, reasons):
        if reason:
            status[int(frame)] = reason
    valid = np.array([not reason for reason in reasons], dtype=bool)
    track = PoseTrack(base.t_ns, base.x, base.y, base.yaw, valid)
    counts: dict[str, int] = {}
    for code in status:
        counts[code] = counts.get(code, 0) + 1
    all_notes = list(notes)
    if registration.voxel_size_m is not None:
        config = replace(config, voxel_size_m=registration.voxel_size_m)
        all_notes.append(f'kiss-icp voxel size {registration.voxel_size_m:g} m')
    skipped = counts.get('empty', 0) + counts.get('tiny', 0)
    if skipped:
        all_notes.append(f'{skipped} lidar frame(s) skipped: empty or fewer than '
                         f'{config.min_points} points (C10)')
    if counts.get('no_deskew'):
        all_notes.append(f'{counts["no_deskew"]} frame(s) registered without deskew: per-point '
                         'times missing, constant or NaN (C9)')
    if config.stride > 1:
        all_notes.append(f'registered one scan in {config.stride} ({counts.get("stride", 0)} '
                         'scans not registered)')
    all_notes.append(exclusions.summary())
    for check, state in exclusions.checks.items():
        all_notes.append(f'ground-truth check {check}: {state}')
    for note in all_notes:
        _LOG.debug(note)
    return GroundTruth(track, registration.end_ns.copy(), tuple(status), counts, from_cache,
                       tuple(all_notes), config, exclusions.as_dict())


def lidar_ground_truth(frames: Iterable[FrameLike] | Callable[[], Iterable[FrameLike]],
                       extrinsic: np.ndarray, config: IcpConfig | None = None, *,
                       limits: Any = None, wheels: WheelSamples | None = None,
                       imu: ImuSamples | None = None,
                       on_frame: Callable[[int], None] | None = None) -> GroundTruth:
    """Run kiss-icp over lidar frames held or streamed here; return the planar ground truth.

    frames: an iterable of frames (or a callable returning one); extrinsic: T_base_lidar
    (4x4); wheels / imu: the recording's wheel speeds and IMU for the guard (lidar_guard);
    limits: a lidar_guard.GuardLimits. For a recording on disk, prefer
    :func:`skidkin_ros.adapters.lidar_chunks.bag_ground_truth` (chunks, processes, cache).
    """
    config = config or IcpConfig()
    extrinsic = np.asarray(extrinsic, dtype=float)
    if extrinsic.shape != (4, 4) or not np.all(np.isfinite(extrinsic)):
        raise ParameterError('extrinsic must be a finite 4x4 T_base_lidar (m, rotation matrix)')
    source = frames() if callable(frames) else frames
    registration = register_frames(source, config, on_frame=on_frame)
    return guarded_truth(registration, extrinsic, config, limits, wheels=wheels, imu=imu)
