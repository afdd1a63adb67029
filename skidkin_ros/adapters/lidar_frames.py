"""The data of the lidar ground truth: input frames, the stride grid, registrations, results.

One job: the types passed between registering (:mod:`skidkin_ros.adapters.lidar_register`),
the chunks and their cache (:mod:`skidkin_ros.adapters.lidar_chunks`) and the guard, with the
status codes a registration gives each frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from skidkin_ros.adapters.icp_config import IcpConfig
from skidkin_ros.core.drive import PoseTrack

__all__ = ['FrameGrid', 'FrameLike', 'GroundTruth', 'REGISTERED', 'Registration',
           'REGISTRATION_CODES']

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


class FrameLike(Protocol):
    """Any lidar frame: stamp, points (N, 3) in the lidar frame, times, end of sweep."""

    stamp_ns: int
    xyz: np.ndarray
    t_rel_s: np.ndarray | None
    end_ns: int


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
