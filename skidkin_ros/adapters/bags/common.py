"""Shared pieces of the bag readers: message type names, defaults, stamps, summaries."""

from __future__ import annotations

from bisect import bisect_right
from dataclasses import dataclass
from pathlib import Path
import sqlite3
import struct
from typing import Any, Sequence

import apsw
import numpy as np
from rosbags.rosbag1 import ReaderError as ReaderError1
from rosbags.rosbag2.errors import ReaderError
from rosbags.serde import SerdeError

from skidkin_ros.core.odometry.schema import node_default
from skidkin_ros.core.timeunits import NS_PER_S
from skidkin_ros.errors import DataError, RecordingError


JOINT_STATE = 'sensor_msgs/msg/JointState'
FLOAT64 = 'std_msgs/msg/Float64'
POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
IMU = 'sensor_msgs/msg/Imu'
ODOMETRY = 'nav_msgs/msg/Odometry'
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
POSE_WITH_COVARIANCE = 'geometry_msgs/msg/PoseWithCovarianceStamped'
TF_MESSAGE = 'tf2_msgs/msg/TFMessage'

STORAGE_SUFFIXES = ('.db3', '.mcap')
ROS1_SUFFIX = '.bag'
DEFAULT_MAX_CORRUPT = 10
DEFAULT_MAX_WHEEL_SPEED_RAD_S = node_default('max_wheel_speed')
DEFAULT_PAIR_TOLERANCE_S = node_default('pair_tolerance')
DEFAULT_MAX_WHEEL_ACCELERATION = node_default('max_wheel_acceleration')
DEFAULT_MAX_DT_S = node_default('max_dt')
# A damaged storage region is jumped over in doubling steps up to this much bag time.
MAX_JUMP_NS = 600 * NS_PER_S
# Header stamps may run on another clock than the bag (sim time), but their offset from the
# receive time does not jump by more than this between two clouds.
MAX_STAMP_JUMP_S = 5.0

# Errors a storage plugin can raise mid-iteration on a damaged file (rosbags does not wrap them).
STORAGE_ERRORS = (ReaderError, ReaderError1, apsw.Error, sqlite3.Error, OSError, struct.error,
                  ValueError, OverflowError, IndexError, EOFError, KeyError)
# Errors of decoding one message's bytes.
DECODE_ERRORS = (SerdeError, UnicodeDecodeError, struct.error, ValueError, IndexError,
                 OverflowError, TypeError)


class NoWheelInputError(RecordingError):
    """A recording without any wheel input (no JointState, Float64 pair or odometry named)."""


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


def stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * NS_PER_S + int(header.stamp.nanosec)


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


class MetadataError(RecordingError):
    """A rosbag2 folder whose metadata.yaml cannot be read (its storage files may be fine)."""


# How rosbags' Reader.open begins the message of an unreadable or incomplete metadata.yaml.
METADATA_ERRORS = ('Could not load YAML', 'Could not read metadata', 'A metadata key is missing',
                   'Invalid bag metadata')


def storage_remedy(path: Path) -> str:
    if path.suffix == ROS1_SUFFIX:
        return (f'a damaged ROS 1 bag; on a ROS 1 machine `rosbag reindex {path}` rebuilds its '
                'index, `rosbag check` says what is wrong')
    if path.suffix == '.mcap':
        return (f'it looks truncated (recording killed?); recover it with '
                f'`mcap recover {path} -o recovered.mcap`, or `ros2 bag reindex` its folder')
    return (f'it is truncated or malformed; try `sqlite3 {path} ".recover" | sqlite3 '
            'recovered.db3` then `ros2 bag reindex` on the folder')
