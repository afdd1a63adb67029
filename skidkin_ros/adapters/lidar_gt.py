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

Where each part lives: the settings in :mod:`~skidkin_ros.adapters.icp_config`, the data types
in :mod:`~skidkin_ros.adapters.lidar_frames`, the registration loop in
:mod:`~skidkin_ros.adapters.lidar_register`, the quality measures in
:mod:`~skidkin_ros.adapters.lidar_quality`; this module turns a registration into the planar,
guarded ground truth and re-exports their API.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import logging
from typing import Any, Callable, Iterable

import numpy as np

from skidkin_ros.adapters.icp_config import (auto_voxel_size, IcpConfig,  # noqa: F401
                                             VOXEL_PER_SPACING)
from skidkin_ros.adapters.lidar_frames import (FrameGrid, FrameLike, GroundTruth,  # noqa: F401
                                               REGISTERED, Registration, REGISTRATION_CODES)
from skidkin_ros.adapters.lidar_quality import registration_quality  # noqa: F401
from skidkin_ros.adapters.lidar_register import check_point_times, register_frames  # noqa: F401
from skidkin_ros.core.drive import ImuSamples, PoseTrack, WheelSamples
from skidkin_ros.core.rigid import planar_poses
from skidkin_ros.errors import ParameterError

__all__ = ['auto_voxel_size', 'BaseTrack', 'FrameGrid', 'FrameLike', 'GroundTruth',
           'guarded_truth', 'IcpConfig', 'Registration', 'REGISTRATION_CODES',
           'check_point_times', 'lidar_ground_truth', 'register_frames', 'registration_quality',
           'track_from_registration']

_LOG = logging.getLogger(__name__)


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
