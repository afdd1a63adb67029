"""Turn a SOURCE (a rosbag2 or ROS 1 recording, or a CSV trajectory table) into ``Drive`` objects.

A bag gives its wheel speeds (JointState, two Float64 topics, or a drive controller's Odometry
twist with the controller's geometry), its IMU when present, and ground truth from the lidar
through kiss-icp (``ground_truth='icp'``), from a pose topic (nav_msgs/Odometry,
geometry_msgs/PoseStamped or PoseWithCovarianceStamped), or none (``'none'``: prediction only).
A table gives one Drive per ``segment``. Decisions taken on the user's behalf (auto-selected
topics and joints, skipped messages, cache hits) are collected in ``notes`` for the CLI to print.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import logging
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from skidkin_ros.adapters.bag_reader import check_overlap, NoWheelInputError, open_recording
from skidkin_ros.adapters.bags.common import ROS1_SUFFIX, STORAGE_SUFFIXES
from skidkin_ros.adapters.icp_selfcheck import SelfCheckOptions
from skidkin_ros.adapters.lidar_chunks import bag_ground_truth, ChunkOptions
from skidkin_ros.adapters.lidar_gt import IcpConfig
from skidkin_ros.adapters.table import read_table
from skidkin_ros.core.drive import Drive, PoseTrack, WheelSamples
from skidkin_ros.core.odometry.controller import ControllerGeometry
from skidkin_ros.core.odometry.schema import node_default
from skidkin_ros.errors import DataError, RecordingError

__all__ = ['SourceOptions', 'LoadedSource', 'load_source', 'load_sources', 'is_table',
           'extrinsic_from_xyz_rpy']

_LOG = logging.getLogger(__name__)
TABLE_SUFFIXES = ('.csv', '.tsv', '.txt')
IMU = 'sensor_msgs/msg/Imu'


def is_table(path: Path) -> bool:
    return path.suffix.lower() in TABLE_SUFFIXES


def _check_not_a_folder_of_tables(path: Path) -> None:
    """Refuse a folder that holds CSV tables and no recording, naming what to pass.

    A table is read from its file; its folder (``data/husky``) would otherwise be opened as a
    rosbag2 and refused with a message about metadata.yaml that does not say what to pass.
    """
    if not path.is_dir() or (path / 'metadata.yaml').exists():
        return
    entries = sorted(path.iterdir())
    if any(p.suffix in (*STORAGE_SUFFIXES, ROS1_SUFFIX) for p in entries):
        return
    tables = [p for p in entries if p.suffix.lower() in ('.csv', '.tsv') and p.is_file()]
    if not tables:
        return
    names = ', '.join(str(p) for p in tables[:5])
    # `skidkin simulate --out runs/a` writes runs/a/ and runs/a_truth.csv side by side: the
    # parent holds recordings too, and the one meant may be either.
    recordings = [p for p in entries if p.is_dir() and _holds_recording(p)]
    if recordings:
        folders = ', '.join(str(p) for p in recordings[:5])
        raise RecordingError(f'{path} is not a recording: it holds recording folder(s) '
                             f'({folders}) and trajectory table(s) ({names}); pass one of them')
    raise RecordingError(f'{path} is a folder of trajectory tables, not a recording: pass '
                         f'the table file itself ({names})')


def _holds_recording(folder: Path) -> bool:
    """Tell whether a folder is a recording: metadata.yaml, storage files or ROS 1 bags."""
    try:
        return (folder / 'metadata.yaml').is_file() or any(
            p.suffix in (*STORAGE_SUFFIXES, ROS1_SUFFIX) and p.is_file() for p in folder.iterdir())
    except OSError:  # unreadable: not one to name
        return False


def extrinsic_from_xyz_rpy(values: Sequence[float]) -> np.ndarray:
    """T_base_lidar (4x4) from x, y, z (m) and roll, pitch, yaw (rad), ZYX convention."""
    if len(values) != 6 or not all(np.isfinite(values)):
        raise DataError('the extrinsic needs 6 finite numbers: x y z (m) roll pitch yaw (rad) '
                        'of the lidar in base_link')
    x, y, z, roll, pitch, yaw = (float(v) for v in values)
    out = np.eye(4)
    # Intrinsic z-y'-x'' (yaw, then pitch, then roll): R = Rz(yaw) Ry(pitch) Rx(roll), as URDF
    # and tf2 read rpy.
    from scipy.spatial.transform import Rotation  # scipy.spatial: only for an extrinsic

    out[:3, :3] = Rotation.from_euler('ZYX', [yaw, pitch, roll]).as_matrix()
    out[:3, 3] = [x, y, z]
    return out


@dataclass(frozen=True)
class SourceOptions:
    """How to read a source: topics, joints, ground truth, extrinsic and the ICP settings.

    ``chunks``: how the lidar ground truth is cut and run (processes, a Dask cluster);
    ``icp_check``: self-check the fast kiss-icp settings (adapters.icp_selfcheck);
    ``on_progress(frames done, frames total)`` follows its registration.
    """

    wheel_topic: str | None = None
    left_topic: str | None = None
    right_topic: str | None = None
    left_joints: tuple[str, ...] | None = None
    right_joints: tuple[str, ...] | None = None
    lidar_topic: str | None = None
    imu_topic: str | None = None
    ground_truth: str = 'icp'
    base_frame: str = 'base_link'
    extrinsic: np.ndarray | None = None
    cache_dir: Path | None = None
    on_progress: Callable[[int, int], None] | None = None
    icp: IcpConfig = field(default_factory=IcpConfig)
    chunks: ChunkOptions = field(default_factory=ChunkOptions)
    icp_check: bool = True
    max_wheel_speed_rad_s: float = node_default('max_wheel_speed')
    pair_tolerance_s: float = node_default('pair_tolerance')
    max_wheel_acceleration: float = node_default('max_wheel_acceleration')
    max_dt_s: float = node_default('max_dt')
    wheel_signal: str = 'velocity'
    min_overlap_s: float = 10.0
    msg_files: tuple[Path, ...] = ()
    odometry_topic: str | None = None
    controller: ControllerGeometry | None = None
    # groundtruth: a bag without any wheel input is read (the wheel check is skipped).
    wheels_optional: bool = False


@dataclass
class LoadedSource:
    """What a source gave: its drives, the wheel input used, and the notes for the user."""

    path: Path
    kind: str
    drives: list[Drive]
    notes: list[str] = field(default_factory=list)
    wheel_input: dict[str, Any] = field(default_factory=dict)
    truth_info: dict[str, Any] = field(default_factory=dict)


def load_sources(paths: Sequence[str | Path], options: SourceOptions,
                 need_truth: bool = True) -> list[LoadedSource]:
    return [load_source(path, options, need_truth) for path in paths]


def load_source(path: str | Path, options: SourceOptions,
                need_truth: bool = True) -> LoadedSource:
    source = Path(path)
    if is_table(source):
        drives = read_table(source)
        rows = sum(len(d.wheels) for d in drives)
        notes = [f'{source}: trajectory table, {len(drives)} segment(s), {rows} rows']
        if options.wheel_signal != 'velocity':
            notes.append(f'{source}: a table holds wheel speeds only; wheel_signal '
                         f'{options.wheel_signal} does not apply to it, its speeds are used')
        return LoadedSource(source, 'table', drives, notes)
    _check_not_a_folder_of_tables(source)
    return _load_bag(source, options, need_truth)


def _load_bag(path: Path, options: SourceOptions, need_truth: bool) -> LoadedSource:
    with open_recording(path, msg_files=options.msg_files) as rec:
        try:
            wheels = _read_wheels(rec, options)
        except NoWheelInputError as err:
            if not options.wheels_optional:
                raise
            wheels = None
            rec.notes.append(f'{path}: no wheel input ({str(err).split(". Topics")[0]}); the '
                             "ground truth's gross wheel check is skipped, ICP's own quality "
                             'and the IMU (when recorded) still judge the poses')
        if wheels is not None and len(wheels) < 2:
            raise DataError(f'{path}: fewer than 2 wheel samples; nothing to integrate')
        imu = None
        imu_topics = [t for t, m in rec.topics().items() if m == IMU]
        if options.imu_topic or len(imu_topics) == 1:
            imu = rec.read_imu(options.imu_topic)
        truth = None
        truth_info: dict[str, Any] = {'ground_truth': 'none'}
        if need_truth and options.ground_truth == 'icp':
            truth, truth_info = _icp_truth(rec, path, wheels, imu, options)
        elif need_truth and options.ground_truth != 'none':
            truth = rec.read_pose_track(options.ground_truth)
            truth_info = {'ground_truth': f'pose topic {options.ground_truth}'}
        if truth is not None and wheels is not None:
            check_overlap((int(wheels.t_ns[0]), int(wheels.t_ns[-1])),
                          (int(truth.t_ns[0]), int(truth.t_ns[-1])),
                          names=('wheel speeds', 'ground truth'),
                          min_seconds=options.min_overlap_s)
        if wheels is None:
            wheels = WheelSamples(np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0))
        drive = Drive(path.name, wheels, truth, imu, {'source': str(path)})
        return LoadedSource(path, 'bag', [drive], list(rec.notes), dict(rec.wheel_input),
                            truth_info)


def _read_wheels(rec, options: SourceOptions) -> WheelSamples:
    return rec.read_wheels(options.wheel_topic, left_joints=options.left_joints,
                           right_joints=options.right_joints,
                           left_topic=options.left_topic, right_topic=options.right_topic,
                           max_wheel_speed_rad_s=options.max_wheel_speed_rad_s,
                           pair_tolerance_s=options.pair_tolerance_s,
                           max_wheel_acceleration=options.max_wheel_acceleration,
                           max_dt_s=options.max_dt_s, wheel_signal=options.wheel_signal,
                           odometry_topic=options.odometry_topic,
                           controller=options.controller)


def _icp_truth(rec, path: Path, wheels, imu, options: SourceOptions) -> tuple[PoseTrack, dict]:
    lidar_topic = rec.select(['sensor_msgs/msg/PointCloud2'], options.lidar_topic, 'lidar')
    first = next(iter(rec.iter_lidar(lidar_topic)), None)
    if first is None:
        raise RecordingError(f'{path}: lidar topic {lidar_topic} holds no usable cloud')
    extrinsic = options.extrinsic
    if extrinsic is None:
        extrinsic = rec.read_extrinsic(options.base_frame, first.frame_id)
        if extrinsic is None:
            raise DataError(
                f'{path}: no /tf_static transform from {options.base_frame} to the lidar frame '
                f'{first.frame_id!r}; give it with --extrinsic X Y Z ROLL PITCH YAW (m, rad). '
                'Without it the lidar offset would be confounded with the model (x_v).')
    result = bag_ground_truth(rec, path, lidar_topic, extrinsic, options.icp, options.chunks,
                              wheels=wheels, imu=imu, cache_dir=options.cache_dir,
                              on_progress=options.on_progress,
                              check=SelfCheckOptions(enabled=options.icp_check))
    rec.notes.extend(result.notes)
    info = {'ground_truth': f'kiss-icp on {lidar_topic}', 'frames': dict(result.counts),
            'from_cache': bool(result.from_cache), 'excluded': result.excluded}
    _LOG.debug('ICP frame counts: %s', result.counts)
    return result.track, info
