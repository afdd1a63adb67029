"""The recording object: every reader job joined in one class, and open_recording."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from skidkin_ros.adapters.bags.common import DEFAULT_MAX_CORRUPT
from skidkin_ros.adapters.bags.floats import FloatPairMixin
from skidkin_ros.adapters.bags.imu import ImuMixin
from skidkin_ros.adapters.bags.lidar import LidarMixin
from skidkin_ros.adapters.bags.odom_wheels import OdomWheelsMixin
from skidkin_ros.adapters.bags.open import BagStorage
from skidkin_ros.adapters.bags.poses import PosesMixin
from skidkin_ros.adapters.bags.stream import StreamMixin
from skidkin_ros.adapters.bags.topics import TopicsMixin
from skidkin_ros.adapters.bags.wheels import WheelsMixin


class BagRecording(WheelsMixin, FloatPairMixin, OdomWheelsMixin, LidarMixin, ImuMixin,
                   PosesMixin, TopicsMixin, StreamMixin, BagStorage):
    """An open recording (rosbag2 or ROS 1): summary, topic selection, and streaming readers.

    Use :func:`open_recording`; close it (or use ``with``). ``notes`` collects decisions and
    counts worth telling the user (auto-selected topics and joints, dropped messages).
    """


def open_recording(path: Path | str, *, max_corrupt: int = DEFAULT_MAX_CORRUPT,
                   msg_files: Sequence[Path | str] = ()) -> BagRecording:
    """Open a rosbag2 folder, or a single .db3 / .mcap file, for reading.

    ``max_corrupt``: corrupt messages / storage errors skipped per pass before giving up.
    ``msg_files``: extra ``<package>/msg/<Name>.msg`` definitions for custom types.
    """
    return BagRecording(path, max_corrupt=max_corrupt, msg_files=msg_files)
