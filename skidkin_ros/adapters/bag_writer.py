"""Write rosbag2 recordings (sqlite3 or mcap) of the topics skidkin_ros reads.

Used by the simulator and the tests: every bag a test reads is written here into a temp folder,
so no recording is committed. ``t_ns`` is the bag receive time, ``stamp_ns`` the header stamp
(default: ``t_ns``); both are integer nanoseconds.

Example::

    with BagWriter(tmp_path / 'drive') as bag:
        bag.write_joint_state('/joint_states', t_ns, ['left_wheel', 'right_wheel'], [1.0, 1.2])
        bag.write_pointcloud('/points', t_ns, 'lidar', xyz, t_point=t_rel_s)
"""

from __future__ import annotations

import logging
from pathlib import Path
import shutil
from types import TracebackType
from typing import Any, Sequence

import numpy as np
from rosbags.interfaces import (
    Connection,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.errors import WriterError
from rosbags.typesys import get_typestore, Stores

from skidkin_ros.adapters.pointcloud import columns_from_mapping, pack_points
from skidkin_ros.core.rotation import yaw_to_quaternion
from skidkin_ros.core.timeunits import NS_PER_S
from skidkin_ros.errors import OutputError, RecordingError

__all__ = ['BagWriter', 'TF_STATIC_QOS']

_STORAGES = {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}
# Files a rosbag2 folder may hold; overwrite refuses folders with anything else in them.
_BAG_SUFFIXES = ('.yaml', '.db3', '.db3-shm', '.db3-wal', '.db3-journal', '.mcap', '.zstd')

# What `ros2 bag record` stores for /tf_static: reliable, transient local, keep last 1.
_UNSET = QosTime(0, 0)
TF_STATIC_QOS = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE,
                    QosDurability.TRANSIENT_LOCAL, _UNSET, _UNSET, QosLiveliness.AUTOMATIC,
                    _UNSET, False)


def _check_time(t_ns: int, what: str) -> int:
    if isinstance(t_ns, (bool, float)) or not isinstance(t_ns, (int, np.integer)):
        raise RecordingError(f'{what} must be integer nanoseconds, got {t_ns!r}; '
                             'convert seconds with int(round(t_s * 1e9))')
    if t_ns < 0:
        raise RecordingError(f'{what} must be >= 0 ns, got {t_ns}')
    return int(t_ns)


def _prepare_target(path: Path, overwrite: bool) -> None:
    if not path.exists():
        return
    if not overwrite:
        raise OutputError(f'{path} already exists; pass overwrite=True (or --force) to replace '
                          'it, or choose another path')
    if path.is_dir():
        strangers = [child.name for child in path.iterdir()
                     if not child.name.endswith(_BAG_SUFFIXES)]
        if strangers:
            raise OutputError(f'{path} exists and holds files that are not part of a rosbag2 '
                              f'({sorted(strangers)[:5]}); refusing to delete it')
        shutil.rmtree(path)
    else:
        path.unlink()


class BagWriter:
    """A rosbag2 writer for the message types skidkin_ros uses (a context manager).

    The bag folder is created on entering (or :meth:`open`); an existing path is refused unless
    ``overwrite``. One connection is created per topic, on its first message.
    """

    def __init__(self, path: Path, storage: str = 'sqlite3', overwrite: bool = False) -> None:
        if storage not in _STORAGES:
            raise RecordingError(f'unknown bag storage {storage!r}; expected one of '
                                 f'{sorted(_STORAGES)}')
        self.path = Path(path)
        self.storage = storage
        self.overwrite = overwrite
        self.typestore = get_typestore(Stores.ROS2_JAZZY)
        self._writer: Writer | None = None
        self._connections: dict[str, Connection] = {}
        self._types = self.typestore.types

    # -- life cycle -----------------------------------------------------------------------------
    def open(self) -> 'BagWriter':  # noqa: A003 - the usual name, as in rosbags
        """Create the bag folder and open the storage; return self."""
        if self._writer is not None:
            return self
        _prepare_target(self.path, self.overwrite)
        try:
            writer = Writer(self.path, version=Writer.VERSION_LATEST,
                            storage_plugin=_STORAGES[self.storage])
            writer.open()
        except (WriterError, OSError) as err:
            raise OutputError(f'cannot create bag {self.path}: {err}') from err
        self._writer = writer
        return self

    def close(self) -> None:
        """Write the index and metadata.yaml and close the bag."""
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.close()

    def __enter__(self) -> 'BagWriter':
        return self.open()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None:
        # Close even on error: what was written stays readable, like an interrupted recording
        # that rosbag2 closed cleanly. A failing close must not hide the original error.
        if exc_type is None:
            self.close()
            return
        try:
            self.close()
        except Exception:  # noqa: B902 - the original exception is the one to report
            logging.getLogger(__name__).warning('closing %s after an error failed', self.path)

    # -- generic --------------------------------------------------------------------------------
    def connection(self, topic: str, msgtype: str, msgdef: str | None = None,
                   rihs01: str | None = None, qos: Sequence[Qos] = ()) -> Connection:
        """Return the topic's connection, creating it (with this message type) on first use."""
        if self._writer is None:
            raise RecordingError(f'bag {self.path} is not open; use "with BagWriter(...) as bag"')
        existing = self._connections.get(topic)
        if existing is not None:
            if existing.msgtype != msgtype:
                raise RecordingError(f'topic {topic} already carries {existing.msgtype}, '
                                     f'cannot also write {msgtype} on it')
            return existing
        if msgdef is None:
            conn = self._writer.add_connection(topic, msgtype, typestore=self.typestore,
                                               offered_qos_profiles=qos)
        else:
            conn = self._writer.add_connection(topic, msgtype, msgdef=msgdef,
                                               rihs01=rihs01 or 'RIHS01_' + '0' * 64,
                                               offered_qos_profiles=qos)
        self._connections[topic] = conn
        return conn

    def write_message(self, topic: str, t_ns: int, msg: Any, qos: Sequence[Qos] = ()) -> None:
        """Serialize and write any message of the typestore (ROS 2 Jazzy types)."""
        t_ns = _check_time(t_ns, f'{topic} receive time')
        conn = self.connection(topic, msg.__msgtype__, qos=qos)
        self._writer.write(conn, t_ns, self.typestore.serialize_cdr(msg, msg.__msgtype__))

    def write_raw(self, topic: str, msgtype: str, t_ns: int, data: bytes,
                  msgdef: str | None = None) -> None:
        """Write already-serialized bytes (e.g. a custom type given by its .msg text)."""
        t_ns = _check_time(t_ns, f'{topic} receive time')
        conn = self.connection(topic, msgtype, msgdef=msgdef)
        self._writer.write(conn, t_ns, bytes(data))

    # -- helpers --------------------------------------------------------------------------------
    def _header(self, t_ns: int, stamp_ns: int | None, frame_id: str) -> Any:
        stamp = _check_time(t_ns if stamp_ns is None else stamp_ns, 'header stamp')
        time_type = self._types['builtin_interfaces/msg/Time']
        time = time_type(sec=stamp // NS_PER_S, nanosec=stamp % NS_PER_S)
        return self._types['std_msgs/msg/Header'](stamp=time, frame_id=frame_id)

    def _vector3(self, values: Sequence[float]) -> Any:
        x, y, z = (float(v) for v in values)
        return self._types['geometry_msgs/msg/Vector3'](x=x, y=y, z=z)

    def _quaternion(self, xyzw: Sequence[float]) -> Any:
        x, y, z, w = (float(v) for v in xyzw)
        return self._types['geometry_msgs/msg/Quaternion'](x=x, y=y, z=z, w=w)

    def _planar_pose(self, x: float, y: float, yaw: float) -> Any:
        point = self._types['geometry_msgs/msg/Point'](x=float(x), y=float(y), z=0.0)
        return self._types['geometry_msgs/msg/Pose'](
            position=point, orientation=self._quaternion(yaw_to_quaternion(yaw)))

    # -- typed writers ----------------------------------------------------------------------------
    def write_joint_state(self, topic: str, t_ns: int, names: Sequence[str],
                          velocities: Sequence[float], positions: Sequence[float] | None = None,
                          stamp_ns: int | None = None) -> None:
        """Write a sensor_msgs/JointState (velocities in rad/s, positions in rad)."""
        velocity = np.asarray(velocities, dtype=np.float64).reshape(-1)
        position = (np.zeros(0) if positions is None
                    else np.asarray(positions, dtype=np.float64).reshape(-1))
        if velocity.size != len(names) or position.size not in (0, len(names)):
            raise RecordingError(f'joint state on {topic}: {len(names)} names but '
                                 f'{velocity.size} velocities / {position.size} positions')
        msg = self._types['sensor_msgs/msg/JointState'](
            header=self._header(t_ns, stamp_ns, ''), name=list(names), position=position,
            velocity=velocity, effort=np.zeros(0))
        self.write_message(topic, t_ns, msg)

    def write_float64(self, topic: str, t_ns: int, value: float) -> None:
        """Write a std_msgs/Float64 (e.g. one wheel's speed in rad/s)."""
        self.write_message(topic, t_ns, self._types['std_msgs/msg/Float64'](data=float(value)))

    def write_pointcloud(self, topic: str, t_ns: int, frame_id: str, xyz: np.ndarray,
                         t_point: np.ndarray | None = None, time_field: str = 't',
                         time_dtype: str = 'float32', stamp_ns: int | None = None,
                         extra_fields: dict[str, np.ndarray] | None = None) -> None:
        """Write an unorganized sensor_msgs/PointCloud2 (x, y, z float32, then t, then extras).

        ``t_point`` holds per-point times in whatever unit and reference the caller chose; they
        are written as-is with ``time_dtype`` (e.g. 'uint32' ns relative, 'float64' absolute s).
        """
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise RecordingError(f'point cloud on {topic}: xyz must have shape (N, 3), got '
                                 f'{xyz.shape}')
        columns: list[tuple[str, np.ndarray, Any]] = [
            ('x', xyz[:, 0], np.float32), ('y', xyz[:, 1], np.float32),
            ('z', xyz[:, 2], np.float32)]
        if t_point is not None:
            columns.append((time_field, np.asarray(t_point), np.dtype(time_dtype)))
        columns.extend(columns_from_mapping(extra_fields))
        specs, point_step, data = pack_points(columns)
        field_type = self._types['sensor_msgs/msg/PointField']
        fields = [field_type(name=s.name, offset=s.offset, datatype=s.datatype, count=s.count)
                  for s in specs]
        n_points = xyz.shape[0]
        msg = self._types['sensor_msgs/msg/PointCloud2'](
            header=self._header(t_ns, stamp_ns, frame_id), height=1, width=n_points,
            fields=fields, is_bigendian=False, point_step=point_step,
            row_step=point_step * n_points, data=data,
            is_dense=bool(np.all(np.isfinite(xyz))))
        self.write_message(topic, t_ns, msg)

    def write_imu(self, topic: str, t_ns: int, frame_id: str, angular_velocity: Sequence[float],
                  linear_acceleration: Sequence[float], stamp_ns: int | None = None) -> None:
        """Write a sensor_msgs/Imu without orientation (rad/s, m/s^2)."""
        no_orientation = np.zeros(9)
        no_orientation[0] = -1.0  # REP 145: orientation not provided
        msg = self._types['sensor_msgs/msg/Imu'](
            header=self._header(t_ns, stamp_ns, frame_id),
            orientation=self._quaternion((0.0, 0.0, 0.0, 1.0)),
            orientation_covariance=no_orientation,
            angular_velocity=self._vector3(angular_velocity),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=self._vector3(linear_acceleration),
            linear_acceleration_covariance=np.zeros(9))
        self.write_message(topic, t_ns, msg)

    def write_tf_static(self, t_ns: int, parent: str, child: str, translation: Sequence[float],
                        rotation_xyzw: Sequence[float]) -> None:
        """Write one static transform parent -> child on /tf_static (transient-local QoS)."""
        transform = self._types['geometry_msgs/msg/Transform'](
            translation=self._vector3(translation), rotation=self._quaternion(rotation_xyzw))
        stamped = self._types['geometry_msgs/msg/TransformStamped'](
            header=self._header(t_ns, None, parent), child_frame_id=child, transform=transform)
        msg = self._types['tf2_msgs/msg/TFMessage'](transforms=[stamped])
        self.write_message('/tf_static', t_ns, msg, qos=[TF_STATIC_QOS])

    def write_odometry(self, topic: str, t_ns: int, frame_id: str, child_frame_id: str,
                       x: float, y: float, yaw: float, stamp_ns: int | None = None,
                       twist: Sequence[float] = (0.0, 0.0),
                       pose_covariance: Sequence[float] | None = None) -> None:
        """Write a planar nav_msgs/Odometry: pose (m, rad), twist (v m/s, w rad/s; default 0).

        ``pose_covariance``: its 36 entries (default zeros; a GNSS converter's: huge rotations).
        """
        v, w = (float(value) for value in twist)
        pose_cov = (np.zeros(36) if pose_covariance is None
                    else np.asarray(pose_covariance, dtype=np.float64).reshape(36))
        twist = self._types['geometry_msgs/msg/Twist'](
            linear=self._vector3((v, 0.0, 0.0)), angular=self._vector3((0.0, 0.0, w)))
        msg = self._types['nav_msgs/msg/Odometry'](
            header=self._header(t_ns, stamp_ns, frame_id), child_frame_id=child_frame_id,
            pose=self._types['geometry_msgs/msg/PoseWithCovariance'](
                pose=self._planar_pose(x, y, yaw), covariance=pose_cov),
            twist=self._types['geometry_msgs/msg/TwistWithCovariance'](
                twist=twist, covariance=np.zeros(36)))
        self.write_message(topic, t_ns, msg)

    def write_pose_stamped(self, topic: str, t_ns: int, frame_id: str, x: float, y: float,
                           yaw: float, stamp_ns: int | None = None) -> None:
        """Write a planar geometry_msgs/PoseStamped (m, rad)."""
        msg = self._types['geometry_msgs/msg/PoseStamped'](
            header=self._header(t_ns, stamp_ns, frame_id), pose=self._planar_pose(x, y, yaw))
        self.write_message(topic, t_ns, msg)

    def write_pose_with_covariance(self, topic: str, t_ns: int, frame_id: str, x: float,
                                   y: float, yaw: float, stamp_ns: int | None = None,
                                   covariance: Sequence[float] | None = None) -> None:
        """Write a planar geometry_msgs/PoseWithCovarianceStamped (AMCL's amcl_pose form)."""
        cov = np.zeros(36) if covariance is None else np.asarray(covariance, dtype=np.float64)
        msg = self._types['geometry_msgs/msg/PoseWithCovarianceStamped'](
            header=self._header(t_ns, stamp_ns, frame_id),
            pose=self._types['geometry_msgs/msg/PoseWithCovariance'](
                pose=self._planar_pose(x, y, yaw), covariance=cov.reshape(36)))
        self.write_message(topic, t_ns, msg)
