"""Stream lidar sweeps (sensor_msgs/PointCloud2) as LidarFrames."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np

from skidkin_ros.adapters.bags.common import MAX_STAMP_JUMP_S, POINTCLOUD2, stamp_ns
from skidkin_ros.adapters.pointcloud import interpret_point_times, read_xyz_and_times
from skidkin_ros.core.timeunits import NS_PER_S
from skidkin_ros.errors import RecordingError


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


class LidarMixin:
    """iter_lidar: one LidarFrame at a time."""

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
                stamp = stamp_ns(msg.header)
                try:
                    xyz, raw, is_integer, _ = read_xyz_and_times(msg, time_field)
                except RecordingError as err:
                    # The message decoded: its cloud is unusable, the storage is not damaged.
                    skipped = self._skip_cloud(chosen, err, skipped, kept)
                    continue
                offset = t_ns - stamp
                if (last_offset is not None
                        and abs(offset - last_offset) > MAX_STAMP_JUMP_S * NS_PER_S):
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
