"""Read rosbag2 recordings (sqlite3 or mcap) into core types, streaming and defensively.

Entry point: ``open_recording(path) -> BagRecording`` (a context manager)::

    with open_recording('drive_bag') as bag:
        print(format_summary(bag.summary()))
        wheels = bag.read_wheels()                      # JointState, auto-detected
        for frame in bag.iter_lidar():                  # one LidarFrame at a time
            ...
        extrinsic = bag.read_extrinsic('base_link', 'os_lidar')   # 4x4 or None
        for line in bag.notes:                          # decisions the CLI should print
            print(line)

What it does with faulty recordings (fault rows of docs/fault-matrix.md):

- C1: a missing path is a RecordingError; a folder without metadata.yaml but with .db3 / .mcap
  files is read file by file (in order of their first message) and a note says so; so is a
  folder whose metadata.yaml cannot be read (the note names the error and ``ros2 bag reindex``).
  A path that is neither a file nor a folder (/dev/zero, a pipe) is a RecordingError.
- C2 / C3: a truncated mcap or a malformed sqlite3 file is a RecordingError naming the file and the
  remedy (``mcap recover`` / sqlite ``.recover``, then ``ros2 bag reindex``).
- C4: storage errors met while iterating (apsw, mcap parsing) and undecodable messages are skipped
  and counted; past ``max_corrupt`` skips in one pass, RecordingError. After a storage error the
  stream resumes just past the last good message, jumping ahead (1 ns, 2 ns, 4 ns ... of bag time)
  until the storage reads again, so a few neighbours of the corrupt message may be lost too.
- C5: every decoded value is validated (finite, bounded wheel speeds, non-zero stamps, stamps in
  order) and bad messages are dropped and counted; the counts go to ``notes``. Wheel samples
  whose speed jumps (faster than ``max_wheel_acceleration``: the node's rule, shared in
  :mod:`skidkin_ros.core.odometry.wheels`) are dropped too, and a note names the wheel side at
  fault: no fit and no check of the lidar ground truth against the wheels sees a spike. A topic
  the metadata lists but whose messages cannot be read says so.
  Stamps in order: the longest non-decreasing run of stamps is kept, so one corrupted stamp far
  in the future drops that message only, not everything after it; repeated stamps keep the first.
- C6: a message type neither in ROS 2 Jazzy nor defined in the bag is a RecordingError naming the
  topic and type, asking for the .msg file (``msg_files=`` of open_recording).
- C7: topics are picked by type when not named (exactly one candidate: used, and noted); none,
  several, a wrong type or an empty topic are RecordingErrors listing the topics and types there.
- C8: :func:`check_overlap` refuses two time ranges that barely overlap.
- C19: messages are read one at a time from the storage; nothing holds the whole bag.

Times are integer nanoseconds. ``header.stamp`` is used for the data (wheel speeds, clouds, poses,
imu); the bag receive time only for std_msgs/Float64 wheel topics, which have no header.
"""

from __future__ import annotations

from bisect import bisect_right
from collections import Counter
from dataclasses import dataclass
import logging
import math
from pathlib import Path
import sqlite3
import struct
from types import TracebackType
from typing import Any, Iterator, Sequence

import apsw
import numpy as np
from rosbags.interfaces import Connection, MessageDefinitionFormat
from rosbags.rosbag2 import Reader
from rosbags.rosbag2.errors import ReaderError
from rosbags.serde import SerdeError
from rosbags.typesys import get_types_from_msg, get_typestore, Stores
from scipy.spatial.transform import Rotation

from skidkin_ros.adapters.pointcloud import interpret_point_times, read_xyz_and_times
from skidkin_ros.core.drive import ImuSamples, PoseTrack, WheelSamples
from skidkin_ros.core.odometry.config import node_default
from skidkin_ros.core.odometry.wheels import (check_position_count, check_velocity_count,
                                              drop_jumps, DuplicateJointError, joint_indices,
                                              MalformedMessageError, MissingJointError,
                                              pair_wheel_streams, positions_at, speeds_at,
                                              WheelSignal)
from skidkin_ros.core.rotation import quaternion_to_yaw
from skidkin_ros.errors import DataError, RecordingError

__all__ = [
    'JOINT_STATE',
    'FLOAT64',
    'POINTCLOUD2',
    'IMU',
    'ODOMETRY',
    'POSE_STAMPED',
    'TF_MESSAGE',
    'TopicSummary',
    'LidarFrame',
    'BagRecording',
    'open_recording',
    'format_summary',
    'check_overlap',
    'keep_monotonic',
    'MAX_STAMP_JUMP_S',
]

LOG = logging.getLogger(__name__)

JOINT_STATE = 'sensor_msgs/msg/JointState'
FLOAT64 = 'std_msgs/msg/Float64'
POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
IMU = 'sensor_msgs/msg/Imu'
ODOMETRY = 'nav_msgs/msg/Odometry'
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
TF_MESSAGE = 'tf2_msgs/msg/TFMessage'

STORAGE_SUFFIXES = ('.db3', '.mcap')
DEFAULT_MAX_CORRUPT = 10
DEFAULT_MAX_WHEEL_SPEED_RAD_S = node_default('max_wheel_speed')
DEFAULT_PAIR_TOLERANCE_S = node_default('pair_tolerance')
DEFAULT_MAX_WHEEL_ACCELERATION = node_default('max_wheel_acceleration')
DEFAULT_MAX_DT_S = node_default('max_dt')
NS_PER_S = 1_000_000_000
# A damaged storage region is jumped over in doubling steps up to this much bag time.
_MAX_JUMP_NS = 600 * 10**9
# Header stamps may run on another clock than the bag (sim time), but their offset from the
# receive time does not jump by more than this between two clouds.
MAX_STAMP_JUMP_S = 5.0

# Errors a storage plugin can raise mid-iteration on a damaged file (rosbags does not wrap them).
_STORAGE_ERRORS = (ReaderError, apsw.Error, sqlite3.Error, OSError, struct.error, ValueError,
                   OverflowError, IndexError, EOFError, KeyError)
# Errors of decoding one message's bytes.
_DECODE_ERRORS = (SerdeError, UnicodeDecodeError, struct.error, ValueError, IndexError,
                  OverflowError, TypeError)


@dataclass(frozen=True)
class TopicSummary:
    """One topic of a recording: type, message count, receive-time range (ns) when scanned."""

    topic: str
    msgtype: str
    count: int
    first_ns: int | None = None
    last_ns: int | None = None

    @property
    def duration_s(self) -> float | None:
        if self.first_ns is None or self.last_ns is None:
            return None
        return (self.last_ns - self.first_ns) * 1e-9


@dataclass(frozen=True)
class LidarFrame:
    """One lidar sweep: points in the lidar frame and their times.

    ``t_rel_s`` is each point's time relative to the earliest point (None: the cloud has no
    usable per-point time field); ``end_ns`` the absolute time of the latest point (see
    skidkin_ros.adapters.pointcloud for the rule); ``receive_ns`` the bag receive time.
    """

    stamp_ns: int
    frame_id: str
    xyz: np.ndarray
    t_rel_s: np.ndarray | None
    end_ns: int
    receive_ns: int | None = None


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def keep_monotonic(t_ns: np.ndarray) -> np.ndarray:
    """Return a mask keeping the longest non-decreasing run of stamps, without repeats.

    One corrupted stamp far ahead then costs one sample, not all that follow it.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    n = t.size
    if n == 0:
        return np.zeros(0, dtype=bool)
    if np.all(np.diff(t) > 0):
        return np.ones(n, dtype=bool)
    # Patience sorting for the longest non-decreasing subsequence, O(n log n).
    tails: list[int] = []
    tail_idx: list[int] = []
    parent = np.full(n, -1, dtype=np.int64)
    for i, value in enumerate(t.tolist()):
        pos = bisect_right(tails, value)
        if pos > 0:
            parent[i] = tail_idx[pos - 1]
        if pos == len(tails):
            tails.append(value)
            tail_idx.append(i)
        else:
            tails[pos] = value
            tail_idx[pos] = i
    keep = np.zeros(n, dtype=bool)
    i = tail_idx[-1]
    while i >= 0:
        keep[i] = True
        i = int(parent[i])
    kept = np.flatnonzero(keep)
    repeats = kept[1:][np.diff(t[kept]) == 0]
    keep[repeats] = False
    return keep


def check_overlap(first: tuple[int, int], second: tuple[int, int], *,
                  names: tuple[str, str] = ('wheel speeds', 'lidar'),
                  min_fraction: float = 0.5, min_seconds: float = 10.0) -> tuple[int, int]:
    """Return the common time range (ns) of two ranges, or raise DataError if it is too short.

    The overlap must last ``min_seconds`` and cover ``min_fraction`` of the shorter range.
    """
    (a0, a1), (b0, b1) = (sorted(map(int, first)), sorted(map(int, second)))
    start, end = max(a0, b0), min(a1, b1)
    overlap_s = max(0, end - start) * 1e-9
    shorter_s = max(min(a1 - a0, b1 - b0) * 1e-9, 1e-9)
    fraction = overlap_s / shorter_s

    def describe(lo: int, hi: int) -> str:
        return f'{lo * 1e-9:.3f} s .. {hi * 1e-9:.3f} s ({(hi - lo) * 1e-9:.1f} s)'

    if overlap_s < min_seconds or fraction < min_fraction:
        raise DataError(
            f'{names[0]} ({describe(a0, a1)}) and {names[1]} ({describe(b0, b1)}) overlap for '
            f'{overlap_s:.1f} s, {100 * fraction:.0f} % of the shorter; expected at least '
            f'{min_seconds:.1f} s and {100 * min_fraction:.0f} %. Check that both topics come '
            'from the same drive (and the same clock: sim time vs wall time).')
    return start, end


def format_summary(topics: Sequence[TopicSummary]) -> str:
    """Return a readable table of topics: name, type, count and time range."""
    lines = []
    for item in topics:
        span = ''
        if item.first_ns is not None and item.last_ns is not None:
            span = (f'  {item.first_ns * 1e-9:.3f} .. {item.last_ns * 1e-9:.3f} s '
                    f'({item.duration_s:.1f} s)')
        lines.append(f'{item.topic}  [{item.msgtype}]  {item.count} msgs{span}')
    return '\n'.join(lines) if lines else '(no topics)'


class _MetadataError(RecordingError):
    """A rosbag2 folder whose metadata.yaml cannot be read (its storage files may be fine)."""


# How rosbags' Reader.open begins the message of an unreadable or incomplete metadata.yaml.
_METADATA_ERRORS = ('Could not load YAML', 'Could not read metadata', 'A metadata key is missing',
                    'Invalid bag metadata')


def _storage_remedy(path: Path) -> str:
    if path.suffix == '.mcap':
        return (f'it looks truncated (recording killed?); recover it with '
                f'`mcap recover {path} -o recovered.mcap`, or `ros2 bag reindex` its folder')
    return (f'it is truncated or malformed; try `sqlite3 {path} ".recover" | sqlite3 '
            'recovered.db3` then `ros2 bag reindex` on the folder')


class BagRecording:
    """An open rosbag2 recording: summary, topic selection, and streaming readers.

    Use :func:`open_recording`; close it (or use ``with``). ``notes`` collects decisions and
    counts worth telling the user (auto-selected topics and joints, dropped messages).
    """

    def __init__(self, path: Path | str, *, max_corrupt: int = DEFAULT_MAX_CORRUPT,
                 msg_files: Sequence[Path | str] = ()) -> None:
        self.path = Path(path)
        self.max_corrupt = int(max_corrupt)
        self.notes: list[str] = []
        self.counts: Counter[tuple[str, str]] = Counter()
        # The wheel input actually used by the last read_wheels(), as node parameters (input,
        # left/right_wheel_joints) plus the topics: what a parameters file records.
        self.wheel_input: dict[str, Any] = {}
        self.typestore = get_typestore(Stores.ROS2_JAZZY)
        self._readers: list[Reader] = []
        self.files: list[Path] = []
        for msg_file in msg_files:
            self._register_msg_file(Path(msg_file))
        self._open()

    # -- opening ---------------------------------------------------------------------------------
    def _storage_files(self) -> tuple[list[Path], bool]:
        """Return the paths to open with rosbags and whether they are bare storage files."""
        path = self.path
        if not path.exists():
            raise RecordingError(f'recording {path} does not exist; expected a rosbag2 folder '
                                 '(with metadata.yaml) or a .db3 / .mcap file')
        if path.is_file() and path.name == 'metadata.yaml':
            path = self.path = path.parent
        if not path.is_file() and not path.is_dir():
            raise RecordingError(f'{path} is neither a file nor a folder (a device or a pipe?); '
                                 'expected a rosbag2 folder or a .db3 / .mcap file')
        if path.is_file():
            if path.suffix not in STORAGE_SUFFIXES:
                raise RecordingError(f'{path} is not a rosbag2 recording; expected a folder with '
                                     'metadata.yaml or a .db3 / .mcap file')
            return [path], True
        if (path / 'metadata.yaml').is_file():
            return [path], False
        found = sorted(p for p in path.iterdir() if p.suffix in STORAGE_SUFFIXES and p.is_file())
        if not found:
            present = sorted(p.name for p in path.iterdir())[:10]
            raise RecordingError(f'{path} has no metadata.yaml and no .db3 / .mcap files '
                                 f'(found {present}); point to a rosbag2 folder or file')
        self.notes.append(f'{path} has no metadata.yaml: reading {len(found)} storage file(s) '
                          f'directly ({", ".join(p.name for p in found)}); run `ros2 bag '
                          'reindex` to restore the metadata')
        return found, True

    def _open_one(self, target: Path) -> Reader:
        files = ([target] if target.is_file()
                 else sorted(p for p in target.iterdir() if p.suffix in STORAGE_SUFFIXES))
        errors = (ReaderError, apsw.Error, sqlite3.Error, OSError, struct.error, ValueError,
                  OverflowError, KeyError, IndexError, EOFError, TypeError)
        try:
            reader = Reader(target)
            reader.open()  # reads metadata.yaml of a folder, then the storage
        except errors as err:
            if target.is_dir() and str(err).startswith(_METADATA_ERRORS):
                raise _MetadataError(' '.join(str(err).split())) from err
            names = ', '.join(str(f) for f in files) or str(target)
            remedy = _storage_remedy(files[0]) if files else 'check the recording'
            raise RecordingError(f'cannot open recording {names}: {err} -- {remedy}') from err
        return reader

    def _open(self) -> None:
        targets, bare = self._storage_files()
        try:
            readers = [self._open_one(target) for target in targets]
        except _MetadataError as err:
            readers, targets = self._open_without_metadata(err)
        except RecordingError:
            self.close()
            raise
        self.files = [f for t in targets for f in ([t] if t.is_file() else
                      sorted(p for p in t.iterdir() if p.suffix in STORAGE_SUFFIXES))]
        self._readers = sorted(readers, key=lambda r: r.start_time if r.message_count else 0)
        if bare and len(targets) == 1 and self.path.is_file():
            self.notes.append(f'reading storage file {self.path} directly (no metadata.yaml)')
        self._register_bag_types()

    def _open_without_metadata(self, err: _MetadataError) -> tuple[list[Reader], list[Path]]:
        """Read a folder whose metadata.yaml is broken from its storage files (C1)."""
        folder = self.path
        files = sorted(p for p in folder.iterdir() if p.suffix in STORAGE_SUFFIXES and p.is_file())
        if not files:
            raise RecordingError(f'{folder}/metadata.yaml cannot be read ({err}) and the folder '
                                 'has no .db3 / .mcap file; point to a rosbag2 recording') from err
        try:
            readers = [self._open_one(f) for f in files]
        except RecordingError as inner:
            self.close()
            raise RecordingError(f'{folder}/metadata.yaml cannot be read ({err}), and reading the '
                                 f'storage files directly failed too: {inner}') from inner
        self.notes.append(f'{folder}/metadata.yaml cannot be read ({err}); reading its '
                          f'{len(files)} storage file(s) directly. The storage files are not at '
                          f'fault: run `ros2 bag reindex {folder}` to rewrite the metadata')
        return readers, files

    def close(self) -> None:
        """Close the storage files."""
        readers, self._readers = self._readers, []
        for reader in readers:
            if reader.is_open:
                reader.close()

    def __enter__(self) -> 'BagRecording':
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.close()

    # -- types (C6) ------------------------------------------------------------------------------
    def _register_msg_file(self, path: Path) -> None:
        # The type name comes from the path: <package>/msg/<Name>.msg.
        if not path.is_file() or path.suffix != '.msg' or path.parent.name != 'msg':
            raise RecordingError(f'message definition {path} not found or not named '
                                 '<package>/msg/<Name>.msg')
        msgtype = f'{path.parent.parent.name}/msg/{path.stem}'
        try:
            self.typestore.register(get_types_from_msg(path.read_text(), msgtype))
        except Exception as err:  # noqa: B902 - rosbags' parser raises several kinds
            raise RecordingError(f'cannot parse message definition {path}: {err}') from err

    def _register_bag_types(self) -> None:
        known = self.typestore.fielddefs
        for conn in self._connections():
            if conn.msgtype in known or conn.msgdef.format == MessageDefinitionFormat.NONE:
                continue
            if not conn.msgdef.data.strip():
                continue
            try:
                if conn.msgdef.format == MessageDefinitionFormat.MSG:
                    self.typestore.register(get_types_from_msg(conn.msgdef.data, conn.msgtype))
            except Exception as err:  # noqa: B902 - a broken definition must not block others
                LOG.warning('cannot parse the definition of %s stored in the bag: %s',
                            conn.msgtype, err)

    def _require_type(self, topic: str, msgtype: str) -> None:
        if msgtype not in self.typestore.fielddefs:
            raise RecordingError(
                f'topic {topic} has type {msgtype}, which is not a ROS 2 Jazzy type and has no '
                'definition stored in the bag; supply its .msg file (open_recording(path, '
                f'msg_files=[".../{msgtype}.msg"]), on the command line --msg-file) or '
                'record with a rosbag2 that stores message definitions')

    # -- topics ----------------------------------------------------------------------------------
    def _connections(self) -> list[Connection]:
        return [c for r in self._readers for c in r.connections]

    def topics(self) -> dict[str, str]:
        """Return {topic: message type} of every topic in the recording."""
        result: dict[str, str] = {}
        for conn in self._connections():
            result.setdefault(conn.topic, conn.msgtype)
        return result

    def _count(self, topic: str) -> int:
        return sum(c.msgcount for c in self._connections() if c.topic == topic)

    def summary(self, time_ranges: bool = True) -> list[TopicSummary]:
        """Return every topic with type and count; with ``time_ranges``, first/last receive ns.

        Time ranges need one pass over the bag (streamed, messages not decoded).
        """
        first: dict[str, int] = {}
        last: dict[str, int] = {}
        if time_ranges:
            for conn, t_ns, _ in self._raw_stream(self._connections(), what='summary'):
                first.setdefault(conn.topic, t_ns)
                last[conn.topic] = t_ns
        return [TopicSummary(topic, msgtype, self._count(topic), first.get(topic),
                             last.get(topic))
                for topic, msgtype in sorted(self.topics().items())]

    def _listing(self) -> str:
        items = [f'{topic} [{msgtype}, {self._count(topic)} msgs]'
                 for topic, msgtype in sorted(self.topics().items())]
        return '; '.join(items) if items else 'none'

    def select(self, msgtypes: str | Sequence[str], topic: str | None = None,
               role: str = 'input') -> str:
        """Return the topic to read for ``role``: ``topic`` checked, or the only one of the types.

        Raise RecordingError (listing the topics there) when the named topic is absent, of
        another type or empty, or when no topic or several topics of the types exist.
        """
        wanted = (msgtypes,) if isinstance(msgtypes, str) else tuple(msgtypes)
        present = self.topics()
        kinds = ' or '.join(wanted)
        if topic is not None:
            if topic not in present:
                raise RecordingError(f'{role}: topic {topic} is not in {self.path}; expected a '
                                     f'{kinds} topic. Topics present: {self._listing()}')
            if present[topic] not in wanted:
                raise RecordingError(f'{role}: topic {topic} has type {present[topic]}, expected '
                                     f'{kinds}. Topics present: {self._listing()}')
            chosen = topic
        else:
            candidates = sorted(t for t, m in present.items() if m in wanted)
            if not candidates:
                raise RecordingError(f'{role}: no {kinds} topic in {self.path}. Topics present: '
                                     f'{self._listing()}. Record one, or name another source.')
            if len(candidates) > 1:
                raise RecordingError(f'{role}: several {kinds} topics ({", ".join(candidates)}); '
                                     f'name the one to use. Topics present: {self._listing()}')
            chosen = candidates[0]
            self.notes.append(f'{role}: using {chosen} [{present[chosen]}], the only '
                              f'{kinds} topic')
        if self._count(chosen) == 0:
            raise RecordingError(f'{role}: topic {chosen} has no messages in {self.path}. '
                                 f'Topics present: {self._listing()}')
        self._require_type(chosen, present[chosen])
        return chosen

    # -- streaming (C4, C19) ---------------------------------------------------------------------
    def _skip(self, what: str, reason: str, err: BaseException, skipped: int) -> int:
        skipped += 1
        self.counts[(what, reason)] += 1
        LOG.warning('%s: skipped a %s (%s)', what, reason, err)
        if skipped > self.max_corrupt:
            files = ', '.join(str(f) for f in self.files)
            raise RecordingError(
                f'{what}: more than {self.max_corrupt} corrupt messages or storage errors in '
                f'{files} (last: {err}); the recording is damaged -- '
                f'{_storage_remedy(self.files[0]) if self.files else "re-record it"}') from err
        return skipped

    def _skip_cloud(self, topic: str, err: RecordingError, skipped: int, kept: int) -> int:
        """Count a cloud that decoded but cannot be used; past max_corrupt, say why."""
        skipped += 1
        self.counts[(topic, 'malformed cloud')] += 1
        LOG.warning('%s: skipped a malformed cloud (%s)', topic, err)
        if skipped > self.max_corrupt:
            raise RecordingError(
                f'lidar: {skipped} clouds on {topic} cannot be used ({kept} could), the last '
                f'because: {err}. The recording reads fine: its clouds do not hold what the '
                'lidar ground truth needs (fields x, y, z as float32 or float64, consistent '
                'with point_step and the data); check the driver, or name another --lidar-topic'
            ) from err
        return skipped

    def _raw_stream(self, connections: Sequence[Connection], what: str,
                    start_ns: int | None = None, stop_ns: int | None = None
                    ) -> Iterator[tuple[Connection, int, bytes]]:
        """Yield (connection, receive ns, raw bytes) in bag order, surviving storage errors."""
        skipped = 0
        for reader in self._readers:
            conns = [c for c in connections if c in reader.connections]
            if not conns:
                continue
            resume = start_ns
            jump_ns = 0
            while True:
                try:
                    for conn, t_ns, raw in reader.messages(conns, start=resume, stop=stop_ns):
                        resume = t_ns + 1
                        jump_ns = 0
                        yield conn, t_ns, raw
                    break
                except _STORAGE_ERRORS as err:
                    if jump_ns == 0:
                        # A new incident (some progress since the last one): count it.
                        skipped = self._skip(what, 'storage error', err, skipped)
                        resume = resume if resume is not None else reader.start_time
                        jump_ns = 1
                    elif jump_ns > _MAX_JUMP_NS:
                        raise RecordingError(
                            f'{what}: cannot read past a damaged part of {self.files[0]} '
                            f'({err}) -- {_storage_remedy(self.files[0])}') from err
                    else:
                        # Still stuck at the damaged message: jump further ahead.
                        resume += jump_ns
                        jump_ns *= 2

    def messages(self, topic: str, start_ns: int | None = None, stop_ns: int | None = None
                 ) -> Iterator[tuple[int, Any]]:
        """Yield (receive ns, decoded message) of one topic, lazily, skipping corrupt ones."""
        for _, t_ns, msg in self.messages_of([topic], start_ns, stop_ns):
            yield t_ns, msg

    def messages_of(self, topics: Sequence[str], start_ns: int | None = None,
                    stop_ns: int | None = None) -> Iterator[tuple[str, int, Any]]:
        """Yield (topic, receive ns, decoded message) of several topics in recording order."""
        conns = [c for c in self._connections() if c.topic in topics]
        for topic in topics:
            if not any(c.topic == topic for c in conns):
                raise RecordingError(f'topic {topic} is not in {self.path}. Topics present: '
                                     f'{self._listing()}')
        for conn in conns:
            self._require_type(conn.topic, conn.msgtype)
        skipped = 0
        for conn, t_ns, raw in self._raw_stream(conns, ' + '.join(topics), start_ns, stop_ns):
            try:
                msg = self.typestore.deserialize_cdr(raw, conn.msgtype)
            except _DECODE_ERRORS as err:
                skipped = self._skip(conn.topic, 'undecodable message', err, skipped)
                continue
            yield conn.topic, t_ns, msg

    def _drop(self, topic: str, reason: str, n: int = 1) -> None:
        if n:
            self.counts[(topic, reason)] += n

    def _note_drops(self, topic: str, kept: int) -> None:
        reasons = {reason: n for (t, reason), n in self.counts.items() if t == topic and n}
        if reasons:
            detail = ', '.join(f'{n} {reason}' for reason, n in sorted(reasons.items()))
            self.notes.append(f'{topic}: kept {kept} messages; skipped {detail}')

    # -- wheels ----------------------------------------------------------------------------------
    def read_wheels(self, topic: str | None = None, *,
                    left_joints: Sequence[str] | None = None,
                    right_joints: Sequence[str] | None = None,
                    left_topic: str | None = None, right_topic: str | None = None,
                    max_wheel_speed_rad_s: float = DEFAULT_MAX_WHEEL_SPEED_RAD_S,
                    pair_tolerance_s: float = DEFAULT_PAIR_TOLERANCE_S,
                    max_wheel_acceleration: float = DEFAULT_MAX_WHEEL_ACCELERATION,
                    max_dt_s: float = DEFAULT_MAX_DT_S,
                    wheel_signal: str = 'velocity') -> WheelSamples:
        """Return wheel speeds (rad/s) from a JointState topic or two Float64 topics.

        JointState: stamps from header.stamp (a bag whose stamps are all zero uses receive
        time, noted); a side's speed is the mean of its joints' velocities, as the node takes it
        (:mod:`skidkin_ros.core.odometry.wheels`), or with ``wheel_signal`` position / auto the
        travel between joint positions, by the node's rule (:class:`WheelSignal`); joints default
        to those whose names contain 'left' / 'right'. Float64 pairs: see
        :meth:`_read_float_pair`. Either way, samples whose
        speed jumps faster than ``max_wheel_acceleration`` (rad/s^2) are dropped and noted
        (:meth:`_drop_jumps`).
        """
        if left_topic is not None or right_topic is not None:
            wheels = self._read_float_pair(left_topic, right_topic, max_wheel_speed_rad_s,
                                           pair_tolerance_s)
        else:
            pair = None
            if topic is None and JOINT_STATE not in self.topics().values():
                pair = self._detect_float_pair()
            if pair is not None:
                wheels = self._read_float_pair(*pair, max_wheel_speed_rad_s, pair_tolerance_s)
            else:
                chosen = self.select(JOINT_STATE, topic, 'wheel speeds')
                wheels = self._read_joint_states(chosen, left_joints, right_joints,
                                                 max_wheel_speed_rad_s, wheel_signal)
        return self._drop_jumps(wheels, max_wheel_acceleration, max_dt_s,
                                self.wheel_input.pop('by_position', None))

    def _drop_jumps(self, wheels: WheelSamples, max_acceleration: float,
                    max_dt_s: float, by_position: Sequence[bool] | None = None) -> WheelSamples:
        """Drop samples whose speed jumps, as the node rejects them; name the wheel at fault.

        Speeds measured by encoder positions (``by_position``) are exempt, as in the node.
        """
        keep, sides = drop_jumps(wheels.t_ns, wheels.omega_l, wheels.omega_r, max_acceleration,
                                 max_dt_s, by_position)
        dropped = len(keep) - sum(keep)
        if not dropped:
            return wheels
        source = self.wheel_input.get('topic') or ' and '.join(
            self.wheel_input.get(k, '') for k in ('left_topic', 'right_topic'))
        at_fault = ', '.join(f'{n} on the {side} wheel' for side, n in sides.items() if n)
        self.notes.append(
            f'wheel speeds: dropped {dropped} of {len(keep)} samples of {source} whose speed '
            f'jumped faster than max_wheel_acceleration {max_acceleration:g} rad/s^2 '
            f'({at_fault}): glitches of the wheel readings (the driver or the encoders are at '
            'fault, not the lidar); the node rejects them too')
        mask = np.array(keep, dtype=bool)
        return WheelSamples(wheels.t_ns[mask], np.asarray(wheels.omega_l)[mask],
                            np.asarray(wheels.omega_r)[mask])

    def _detect_joints(self, topic: str, names: Sequence[str]) -> tuple[list[str], list[str]]:
        left = [n for n in names if 'left' in n.lower() and 'right' not in n.lower()]
        right = [n for n in names if 'right' in n.lower() and 'left' not in n.lower()]
        if not left or not right:
            raise RecordingError(f'wheel speeds: cannot tell left from right wheel joints on '
                                 f'{topic} (joints: {list(names)}); name them (left_wheel_joints '
                                 '/ right_wheel_joints)')
        self.notes.append(f'wheel speeds: {topic} joints {left} taken as left, {right} as right '
                          '(names containing left/right)')
        return left, right

    def _read_joint_states(self, topic: str, left_joints: Sequence[str] | None,
                           right_joints: Sequence[str] | None, max_speed: float,
                           wheel_signal: str = 'velocity') -> WheelSamples:
        left = list(left_joints) if left_joints else None
        right = list(right_joints) if right_joints else None
        stamps: list[int] = []
        receive: list[int] = []
        omega_l: list[float] = []
        omega_r: list[float] = []
        positions: list[tuple[tuple[float, ...], tuple[float, ...]] | None] = []
        index_cache: tuple[list[str], tuple[int, ...], tuple[int, ...]] | None = None
        seen_names: set[str] = set()
        read = 0
        for t_ns, msg in self.messages(topic):
            read += 1
            names = list(msg.name)
            seen_names.update(names)
            if left is None or right is None:
                if not any('left' in n.lower() for n in names):
                    self._drop(topic, 'without wheel joints')
                    continue
                auto_left, auto_right = self._detect_joints(topic, names)
                left = left or auto_left
                right = right or auto_right
            if index_cache is None or index_cache[0] != names:
                try:
                    index_cache = (names, *joint_indices(names, left, right))
                except MissingJointError:
                    self._drop(topic, 'without wheel joints')
                    continue
                except DuplicateJointError:  # refused as the node refuses it
                    self._drop(topic, 'with a wheel joint listed twice')
                    continue
            velocity = msg.velocity
            position = None
            if wheel_signal != 'velocity':
                try:
                    if check_position_count(len(names), len(msg.position)):
                        position = positions_at(msg.position, index_cache[1], index_cache[2])
                except MalformedMessageError:
                    self._drop(topic, 'with a position count other than the names')
                    continue
            if position is not None and wheel_signal == 'position' and not len(velocity):
                wl = wr = math.nan  # positions alone are enough
            else:
                try:
                    check_velocity_count(len(names), len(velocity))
                except MalformedMessageError:
                    self._drop(topic, 'without velocities')
                    continue
                wl, wr = speeds_at(velocity, index_cache[1], index_cache[2])
                if wheel_signal == 'velocity' and not (math.isfinite(wl) and math.isfinite(wr)):
                    self._drop(topic, 'non-finite speed')
                    continue
                if abs(wl) > max_speed or abs(wr) > max_speed:
                    self._drop(topic, f'speed beyond {max_speed:g} rad/s')
                    continue
            stamps.append(_stamp_ns(msg.header))
            receive.append(t_ns)
            omega_l.append(wl)
            omega_r.append(wr)
            positions.append(position)
        if not read:
            raise RecordingError(
                f'wheel speeds: no message on {topic} could be read, though the recording lists '
                f'{self._count(topic)}: its messages were removed or cannot be read. Record the '
                'topic again, or check the recording (`ros2 bag reindex` rewrites its metadata)')
        if not stamps:
            wanted = (left or []) + (right or []) or 'named *left* / *right*'
            if self.counts[(topic, 'without wheel joints')] or left is None:
                raise RecordingError(
                    f'wheel speeds: no message on {topic} holds the wheel joints {wanted}; '
                    f'joints seen: {sorted(seen_names)}. Name them (left_wheel_joints / '
                    'right_wheel_joints)')
            raise RecordingError(f'wheel speeds: every message on {topic} was rejected '
                                 f'({self._reasons(topic)}); check the recording')
        t = self._header_or_receive(topic, np.array(stamps, np.int64), np.array(receive, np.int64))
        keep = self._keep_in_order(topic, t)
        self.wheel_input = {'input': 'joint_state', 'topic': topic,
                            'left_wheel_joints': list(left), 'right_wheel_joints': list(right),
                            'wheel_signal': wheel_signal}
        wheels = WheelSamples(t[keep], np.array(omega_l)[keep], np.array(omega_r)[keep])
        if wheel_signal == 'velocity':
            return wheels
        kept = [positions[i] for i in np.flatnonzero(keep)]
        return self._signal_speeds(topic, wheels, kept, wheel_signal, max_speed)

    def _signal_speeds(self, topic: str, wheels: WheelSamples,
                       positions: Sequence[tuple[tuple[float, ...], tuple[float, ...]] | None],
                       wheel_signal: str, max_speed: float) -> WheelSamples:
        """Return the speeds the node integrates under ``wheel_signal`` (WheelSignal's rule)."""
        signal = WheelSignal(wheel_signal, max_speed)
        keep = np.zeros(len(wheels), dtype=bool)
        omega_l = np.asarray(wheels.omega_l, dtype=float).copy()
        omega_r = np.asarray(wheels.omega_r, dtype=float).copy()
        used: Counter[str] = Counter()
        by_position = np.zeros(len(wheels), dtype=bool)
        for i, t_ns in enumerate(wheels.t_ns.tolist()):
            taken = signal.take(t_ns, omega_l[i], omega_r[i], positions[i])
            by_position[i] = taken.by_position
            if taken.warning is not None:
                self.notes.append(f'wheel speeds: {topic} at {t_ns / 1e9:.3f} s: '
                                  f'{taken.warning[1]}')
            if taken.speeds is None:
                self._drop(topic, {'no_position': 'without positions',
                                   'non_finite': 'non-finite position',
                                   'position_range': 'position beyond float resolution',
                                   'implausible': 'position jump beyond max_wheel_speed'
                                   }[taken.cause])
                continue
            omega_l[i], omega_r[i] = taken.speeds
            keep[i] = math.isfinite(omega_l[i]) and math.isfinite(omega_r[i])
            used[signal.in_use] += 1
        self.notes.append(f'wheel speeds: {topic} read with wheel_signal {wheel_signal}: '
                          + ', '.join(f'{n} intervals from the joint {kind}s'
                                      for kind, n in sorted(used.items())))
        self.wheel_input['wheel_signal_used'] = dict(used)
        self.wheel_input['by_position'] = by_position[keep].tolist()
        return WheelSamples(wheels.t_ns[keep], omega_l[keep], omega_r[keep])

    def _reasons(self, topic: str) -> str:
        parts = [f'{n} {reason}' for (t, reason), n in self.counts.items() if t == topic]
        return ', '.join(parts) or (f'no message on {topic} could be read, though the recording '
                                    f'lists {self._count(topic)}')

    def _header_or_receive(self, topic: str, stamps: np.ndarray, receive: np.ndarray
                           ) -> np.ndarray:
        zero = stamps == 0
        if zero.all():
            self.notes.append(f'{topic}: every header.stamp is zero; using the bag receive time')
            return receive
        if zero.any():
            # A zero stamp among real ones is corrupt: push it out of order so it is dropped.
            stamps = stamps.copy()
            stamps[zero] = np.iinfo(np.int64).max
            self._drop(topic, 'zero stamp', int(zero.sum()))
            return stamps
        return stamps

    def _detect_float_pair(self) -> tuple[str, str] | None:
        floats = [t for t, m in self.topics().items() if m == FLOAT64]
        left = [t for t in floats if 'left' in t.lower()]
        right = [t for t in floats if 'right' in t.lower()]
        if len(left) == 1 and len(right) == 1:
            self.notes.append(f'wheel speeds: no JointState topic; using Float64 topics '
                              f'{left[0]} (left) and {right[0]} (right)')
            return left[0], right[0]
        return None

    def _read_float_pair(self, left_topic: str | None, right_topic: str | None,
                         max_speed: float, pair_tolerance_s: float) -> WheelSamples:
        """Pair two std_msgs/Float64 wheel topics on bag receive time, as odom_node pairs them.

        The messages of both topics are taken in recording order and paired by the node's own
        rule (:class:`~skidkin_ros.core.odometry.wheels.WheelPairer`): a left and a right value
        received within ``pair_tolerance_s`` form one sample stamped with the later receive
        time; a value whose partner does not come in time is dropped. A pair with a non-finite
        or implausible value is dropped, as the node's integrator rejects it; of pairs with the
        same stamp the last is kept (the node holds its speeds).
        """
        if left_topic is None or right_topic is None:
            raise RecordingError('wheel speeds from Float64 topics need both a left and a right '
                                 f'topic. Topics present: {self._listing()}')
        if left_topic == right_topic:
            raise RecordingError(f'wheel speeds: the left and right Float64 topics are both '
                                 f'{left_topic}; name one topic per side')
        self.select(FLOAT64, left_topic, 'left wheel speed')
        self.select(FLOAT64, right_topic, 'right wheel speed')
        sides = {left_topic: 'left', right_topic: 'right'}
        events = ((sides[topic], t_ns, float(msg.data))
                  for topic, t_ns, msg in self.messages_of([left_topic, right_topic]))
        pairs, unpaired = pair_wheel_streams(events, pair_tolerance_s * NS_PER_S)
        t_ns: list[int] = []
        omega_l: list[float] = []
        omega_r: list[float] = []
        for t, wl, wr in pairs:
            if not self._plausible_pair(((left_topic, wl), (right_topic, wr)), max_speed):
                continue
            if t_ns and t <= t_ns[-1]:
                if t < t_ns[-1]:  # storage files out of order: the node rejects it as older
                    self._drop(left_topic, 'stamp out of order')
                    continue
                omega_l[-1], omega_r[-1] = wl, wr
                continue
            t_ns.append(t)
            omega_l.append(wl)
            omega_r.append(wr)
        if not t_ns:
            raise RecordingError(
                f'wheel speeds: no valid left/right pair on {left_topic} and {right_topic} '
                f'within pair_tolerance {pair_tolerance_s:g} s ({unpaired} unpaired; '
                f'{self._reasons(left_topic)}; {self._reasons(right_topic)})')
        for topic in (left_topic, right_topic):
            self._note_drops(topic, len(t_ns))
        self.notes.append(f'wheel speeds: {left_topic} and {right_topic} paired on bag receive '
                          f'time within pair_tolerance {pair_tolerance_s:g} s, as odom_node '
                          f'pairs them ({len(t_ns)} samples, {unpaired} value(s) without a '
                          'partner dropped)')
        self.wheel_input = {'input': 'wheel_topics', 'left_topic': left_topic,
                            'right_topic': right_topic}
        return WheelSamples(np.array(t_ns, dtype=np.int64), omega_l, omega_r)

    def _plausible_pair(self, values: Sequence[tuple[str, float]], max_speed: float) -> bool:
        """Tell whether both speeds are finite and within max_speed; count the faulty side."""
        good = True
        for topic, value in values:
            if not math.isfinite(value):
                self._drop(topic, 'non-finite speed')
                good = False
            elif abs(value) > max_speed:
                self._drop(topic, f'speed beyond {max_speed:g} rad/s')
                good = False
        return good

    # -- lidar -----------------------------------------------------------------------------------
    def iter_lidar(self, topic: str | None = None, time_field: str | None = None,
                   start_ns: int | None = None, stop_ns: int | None = None
                   ) -> Iterator[LidarFrame]:
        """Yield LidarFrames one at a time (NaN points dropped; see pointcloud for times).

        Malformed clouds are skipped and counted like corrupt messages (C4). The topic is
        checked at the call (C7), the clouds are read as the iterator is consumed (C19).
        """
        chosen = self.select(POINTCLOUD2, topic, 'lidar')
        return self._lidar_frames(chosen, time_field, start_ns, stop_ns)

    def _lidar_frames(self, chosen: str, time_field: str | None, start_ns: int | None,
                      stop_ns: int | None) -> Iterator[LidarFrame]:
        skipped = 0
        kept = 0
        no_times = 0
        last_stamp = -1
        last_offset: int | None = None
        try:
            for t_ns, msg in self.messages(chosen, start_ns, stop_ns):
                stamp = _stamp_ns(msg.header)
                try:
                    xyz, raw, is_integer, _ = read_xyz_and_times(msg, time_field)
                except RecordingError as err:
                    # The message decoded: its cloud is unusable, the storage is not damaged.
                    skipped = self._skip_cloud(chosen, err, skipped, kept)
                    continue
                offset = t_ns - stamp
                if last_offset is not None and abs(offset - last_offset) > MAX_STAMP_JUMP_S * 1e9:
                    self._drop(chosen, 'stamp far from receive time')
                    continue
                if stamp <= last_stamp:
                    self._drop(chosen, 'stamp out of order or repeated')
                    continue
                last_stamp, last_offset = stamp, offset
                times = None if raw is None else interpret_point_times(raw, is_integer, stamp)
                if times is None:
                    no_times += 1
                kept += 1
                yield LidarFrame(stamp, msg.header.frame_id, xyz,
                                 None if times is None else times.t_rel_s,
                                 stamp if times is None else times.end_ns, t_ns)
        finally:
            if no_times:
                self.notes.append(f'lidar: {no_times} cloud(s) on {chosen} without usable '
                                  'per-point times (no deskew for them)')
            self._note_drops(chosen, kept)

    # -- imu -------------------------------------------------------------------------------------
    def read_imu(self, topic: str | None = None) -> ImuSamples:
        """Return gyro yaw rate (rad/s, angular_velocity.z) and accel x / y (m/s^2)."""
        chosen = self.select(IMU, topic, 'imu')
        rows: list[tuple[int, float, float, float]] = []
        for _, msg in self.messages(chosen):
            row = (_stamp_ns(msg.header), float(msg.angular_velocity.z),
                   float(msg.linear_acceleration.x), float(msg.linear_acceleration.y))
            if not all(math.isfinite(v) for v in row[1:]):
                self._drop(chosen, 'non-finite value')
                continue
            rows.append(row)
        if not rows:
            raise RecordingError(f'imu: no valid message on {chosen} ({self._reasons(chosen)})')
        t = np.array([r[0] for r in rows], dtype=np.int64)
        values = np.array([r[1:] for r in rows], dtype=np.float64)
        keep = self._keep_in_order(chosen, t)
        values = values[keep]
        return ImuSamples(t[keep], values[:, 0], values[:, 1], values[:, 2])

    def _keep_in_order(self, topic: str, t: np.ndarray) -> np.ndarray:
        """Return the mask of strictly increasing stamps; count what it drops on ``topic``."""
        keep = keep_monotonic(t)
        self._drop(topic, 'stamp out of order or repeated', int(np.count_nonzero(~keep)))
        self._note_drops(topic, int(np.count_nonzero(keep)))
        return keep

    # -- poses -----------------------------------------------------------------------------------
    def read_pose_track(self, topic: str | None = None) -> PoseTrack:
        """Return a planar track (x, y m; unwrapped yaw rad) from Odometry or PoseStamped."""
        chosen = self.select((ODOMETRY, POSE_STAMPED), topic, 'ground truth')
        rows: list[tuple[int, float, float, float]] = []
        for _, msg in self.messages(chosen):
            pose = msg.pose.pose if hasattr(msg, 'child_frame_id') else msg.pose
            q = pose.orientation
            yaw = quaternion_to_yaw(q.x, q.y, q.z, q.w)
            row = (_stamp_ns(msg.header), float(pose.position.x), float(pose.position.y), yaw)
            if not all(math.isfinite(v) for v in row[1:]):
                self._drop(chosen, 'non-finite pose')
                continue
            rows.append(row)
        if not rows:
            raise RecordingError(f'ground truth: no valid pose on {chosen} '
                                 f'({self._reasons(chosen)})')
        t = np.array([r[0] for r in rows], dtype=np.int64)
        xyyaw = np.array([r[1:] for r in rows], dtype=np.float64)
        keep = self._keep_in_order(chosen, t)
        xyyaw = xyyaw[keep]
        return PoseTrack(t[keep], xyyaw[:, 0], xyyaw[:, 1], np.unwrap(xyyaw[:, 2]))

    # -- extrinsic -------------------------------------------------------------------------------
    def read_extrinsic(self, base_frame: str, lidar_frame: str, topic: str = '/tf_static'
                       ) -> np.ndarray | None:
        """Return the 4x4 pose of ``lidar_frame`` in ``base_frame`` from /tf_static, or None.

        Chains through intermediate frames in either direction. None (with a note) when the topic
        is absent or no chain joins the two frames.
        """
        base, lidar = base_frame.lstrip('/'), lidar_frame.lstrip('/')
        if topic not in self.topics():
            self.notes.append(f'extrinsic: no {topic} in the recording; give the '
                              f'{base}->{lidar} transform in the configuration')
            return None
        self.select(TF_MESSAGE, topic, 'extrinsic')
        edges: dict[str, dict[str, np.ndarray]] = {}
        for _, msg in self.messages(topic):
            for tf in msg.transforms:
                parent, child = tf.header.frame_id.lstrip('/'), tf.child_frame_id.lstrip('/')
                matrix = _transform_matrix(tf.transform)
                if matrix is None:
                    self._drop(topic, 'non-finite transform')
                    continue
                edges.setdefault(parent, {})[child] = matrix
                edges.setdefault(child, {})[parent] = np.linalg.inv(matrix)
        if base == lidar:
            return np.eye(4)
        chain = _find_chain(edges, base, lidar)
        if chain is None:
            self.notes.append(f'extrinsic: {topic} does not join {base} and {lidar} (frames: '
                              f'{sorted(edges)}); give the transform in the configuration')
            return None
        self.notes.append(f'extrinsic: {base} -> {lidar} from {topic} via {" -> ".join(chain)}')
        result = np.eye(4)
        for a, b in zip(chain[:-1], chain[1:]):
            result = result @ edges[a][b]
        return result


def _transform_matrix(transform: Any) -> np.ndarray | None:
    """Return a geometry_msgs/Transform as a 4x4 matrix; None when not finite or no rotation."""
    t, q = transform.translation, transform.rotation
    quaternion = [float(q.x), float(q.y), float(q.z), float(q.w)]  # scipy's order: x, y, z, w
    translation = [float(t.x), float(t.y), float(t.z)]
    if (not all(math.isfinite(v) for v in translation + quaternion)
            or math.hypot(*quaternion) < 1e-9):
        return None
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_quat(quaternion).as_matrix()  # normalizes the quaternion
    matrix[:3, 3] = translation
    return matrix


def _find_chain(edges: dict[str, dict[str, np.ndarray]], start: str, goal: str
                ) -> list[str] | None:
    previous: dict[str, str | None] = {start: None}
    queue = [start]
    while queue:
        frame = queue.pop(0)
        if frame == goal:
            chain = [goal]
            while previous[chain[-1]] is not None:
                chain.append(previous[chain[-1]])
            return chain[::-1]
        for neighbour in edges.get(frame, {}):
            if neighbour not in previous:
                previous[neighbour] = frame
                queue.append(neighbour)
    return None


def open_recording(path: Path | str, *, max_corrupt: int = DEFAULT_MAX_CORRUPT,
                   msg_files: Sequence[Path | str] = ()) -> BagRecording:
    """Open a rosbag2 folder, or a single .db3 / .mcap file, for reading.

    ``max_corrupt``: corrupt messages / storage errors skipped per pass before giving up.
    ``msg_files``: extra ``<package>/msg/<Name>.msg`` definitions for custom types.
    """
    return BagRecording(path, max_corrupt=max_corrupt, msg_files=msg_files)
