"""Tests of the kiss-icp ground truth on simulated drives (real kiss-icp, real bags)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from skidkin_ros.adapters.lidar_gt import (check_point_times, IcpConfig, lidar_ground_truth,
                                           register_frames)
from skidkin_ros.core.drive import PoseTrack, WheelSamples
from skidkin_ros.core.rigid import change_frame, planar_pose, se3_power
from skidkin_ros.sim import LidarConfig, SimConfig, simulate
from skidkin_ros.sim.accuracy import increment_errors
from skidkin_ros.sim.scene import outdoor_scene

# Dense enough for point-to-point ICP on the synthetic scene (a VLP-16 fires every 0.2 deg).
LIDAR = LidarConfig(azimuth_resolution_deg=0.5, mount_xyz_m=(0.3, 0.1, 0.5), mount_yaw_rad=0.4)
ICP = IcpConfig(voxel_size_m=0.5, max_range_m=50.0)


def truth_errors(sim, track: PoseTrack) -> tuple[np.ndarray, np.ndarray]:
    """Return position (m) and yaw (rad) errors of a track against the truth, first-pose frame."""
    true = sim.pose_at(track.t_ns)
    x0, y0, yaw0 = true[0]
    c, s = math.cos(yaw0), math.sin(yaw0)
    dx, dy = true[:, 0] - x0, true[:, 1] - y0
    pos = np.hypot(track.x - (c * dx + s * dy), track.y - (-s * dx + c * dy))
    yaw = np.abs(track.yaw - (true[:, 2] - yaw0))
    return pos, yaw


@pytest.fixture(scope='module')
def short_drive():
    sim = simulate(SimConfig(duration_s=6.0, seed=2, lidar=LIDAR))
    return sim, list(sim.scans())


def test_extrinsic_convention_recovers_the_base_motion():
    def pose(x, y, yaw, z=0.0):
        transform = np.eye(4)
        transform[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        transform[:3, 3] = (x, y, z)
        return transform

    extrinsic = pose(0.3, 0.1, 0.4, 0.5)
    base_0, base_1 = pose(1.0, 2.0, 0.3), pose(1.5, 2.2, 1.1)
    lidar_motion = (np.linalg.inv(base_0 @ extrinsic) @ (base_1 @ extrinsic))
    recovered = change_frame(lidar_motion, extrinsic)
    assert np.allclose(recovered, np.linalg.inv(base_0) @ base_1)
    x, y, yaw, tilt = planar_pose(recovered)
    assert yaw == pytest.approx(0.8) and tilt == pytest.approx(0.0)
    # the other order (E^-1 T E) would be wrong by the lever arm of the lidar
    wrong = np.linalg.inv(extrinsic) @ lidar_motion @ extrinsic
    assert not np.allclose(wrong[:2, 3], recovered[:2, 3], atol=0.05)


def test_kiss_icp_matches_the_true_trajectory():
    sim = simulate(SimConfig(duration_s=20.0, seed=1, lidar=LIDAR))
    result = lidar_ground_truth(sim.scans(), LIDAR.extrinsic(), ICP)
    track = result.track
    assert len(track) == 199 or len(track) == 200
    assert track.valid.mean() > 0.97
    pos, yaw = truth_errors(sim, track)
    # measured: mean 1.3 cm / 0.11 deg, worst 8 cm / 1.9 deg at abrupt command changes (kiss-icp
    # deskews with the previous frame's motion)
    assert pos.mean() < 0.04 and np.percentile(pos, 95) < 0.08 and pos.max() < 0.25
    assert np.degrees(yaw.mean()) < 0.4 and np.degrees(yaw.max()) < 4.0
    # stamped at the end of each sweep
    assert np.array_equal(track.t_ns[:5], result.frame_stamp_ns[:5])


def test_deskew_helps_on_a_fast_spin():
    sim = simulate(SimConfig(duration_s=5.0, seed=3, script=((4.0, -6.0, 6.0),), lidar=LIDAR))
    scans = list(sim.scans())
    on = lidar_ground_truth(scans, LIDAR.extrinsic(), ICP)
    off = lidar_ground_truth(scans, LIDAR.extrinsic(), dataclasses.replace(ICP, deskew=False))
    _, yaw_on = truth_errors(sim, on.track)
    _, yaw_off = truth_errors(sim, off.track)
    assert np.degrees(yaw_on.mean()) < 0.6
    assert yaw_off.mean() > 2.0 * yaw_on.mean()
    assert math.degrees(on.track.yaw[-1] - on.track.yaw[0]) > 300.0  # it did spin


def test_point_times_are_validated_before_kiss_icp():
    assert check_point_times(np.linspace(0, 0.1, 5), 5, ICP) == (True, '')
    assert not check_point_times(None, 5, ICP)[0]
    assert 'constant' in check_point_times(np.full(5, 0.05), 5, ICP)[1]
    assert 'non-finite' in check_point_times(np.array([0, np.nan, 0.1, 0.1, 0.1]), 5, ICP)[1]
    assert 'times for' in check_point_times(np.linspace(0, 0.1, 4), 5, ICP)[1]
    assert 'unit' in check_point_times(np.linspace(0, 1e8, 5), 5, ICP)[1]


def test_c9_constant_or_nan_times_fall_back_to_no_deskew(short_drive):
    sim, scans = short_drive
    frames = list(scans)
    frames[10] = dataclasses.replace(frames[10], t_rel_s=np.zeros(len(frames[10])))
    frames[20] = dataclasses.replace(frames[20], t_rel_s=np.full(len(frames[20]), np.nan))
    nan_some = frames[30].t_rel_s.copy()
    nan_some[::7] = np.nan
    frames[30] = dataclasses.replace(frames[30], t_rel_s=nan_some)
    frames[40] = dataclasses.replace(frames[40], t_rel_s=None)
    # kiss-icp would abort the process (Sophus: SO3::exp failed) on the first three
    result = lidar_ground_truth(frames, LIDAR.extrinsic(), ICP)
    assert [result.frame_status[i] for i in (10, 20, 30, 40)] == ['no_deskew'] * 4
    assert result.counts['no_deskew'] == 4
    assert result.track.valid.all()
    pos, _ = truth_errors(sim, result.track)
    assert pos.max() < 0.25


def test_c10_empty_and_tiny_clouds_are_skipped_and_their_neighbours_invalid(short_drive):
    sim, scans = short_drive
    frames = list(scans)
    frames[15] = dataclasses.replace(frames[15], xyz=np.zeros((0, 3)), t_rel_s=np.zeros(0))
    frames[35] = dataclasses.replace(frames[35], xyz=frames[35].xyz[:3],
                                     t_rel_s=frames[35].t_rel_s[:3])
    result = lidar_ground_truth(frames, LIDAR.extrinsic(), ICP)
    assert result.frame_status[15] == 'empty' and result.frame_status[35] == 'tiny'
    assert len(result.track) == len(frames) - 2
    assert result.frame_status[14] == 'before_skip' and result.frame_status[16] == 'after_skip'
    assert result.frame_status[34] == 'before_skip' and result.frame_status[36] == 'after_skip'
    assert np.count_nonzero(~result.track.valid) == 4
    assert any('skipped' in note for note in result.notes)


def test_c12_dropped_frame_and_big_jump_are_flagged(short_drive):
    sim, scans = short_drive
    frames = list(scans)
    jumped = frames[40].xyz + np.array([1.5, 0.0, 0.0])
    frames[40] = dataclasses.replace(frames[40], xyz=jumped)
    del frames[20]
    result = lidar_ground_truth(frames, LIDAR.extrinsic(), ICP)
    status = result.frame_status
    assert status[20] == 'gap'  # the frame after the dropped one
    assert status[39] in ('speed', 'yaw_rate')  # the jumped frame (index shifted by the drop)
    invalid = set(np.flatnonzero(~result.track.valid).tolist())
    # kiss-icp's constant-velocity guess carries the jump into a few following frames
    assert 20 in invalid and 39 in invalid
    assert invalid <= {20} | set(range(39, 47))
    pos, _ = truth_errors(sim, result.track)
    assert np.all(pos[:39] < 0.25)


def test_c11_wheels_that_disagree_grossly_are_flagged_without_any_geometry(short_drive):
    sim, scans = short_drive
    wheels = sim.wheels
    agree = lidar_ground_truth(scans, LIDAR.extrinsic(), ICP, wheels=wheels)
    assert agree.track.valid.all()
    assert 'no geometry needed' in ' '.join(agree.notes)
    # the same wheels in other units (a wheel radius 3x larger) change nothing: the scale is
    # fitted against ICP, no geometry enters
    scaled = WheelSamples(wheels.t_ns, wheels.omega_l / 3.0, wheels.omega_r / 3.0)
    again = lidar_ground_truth(scans, LIDAR.extrinsic(), ICP, wheels=scaled)
    assert np.array_equal(again.track.valid, agree.track.valid)
    # the wheels say the robot stood still from 3 s to 4.5 s while it drove: what a lidar stuck
    # in a featureless corridor looks like from the other side
    t_s = (wheels.t_ns - wheels.t_ns[0]) * 1e-9
    frozen = (t_s >= 3.0) & (t_s <= 4.5)
    left, right = wheels.omega_l.copy(), wheels.omega_r.copy()
    left[frozen] = right[frozen] = 0.0
    result = lidar_ground_truth(scans, LIDAR.extrinsic(), ICP,
                                wheels=WheelSamples(wheels.t_ns, left, right))
    flagged = np.flatnonzero(~result.track.valid)
    assert flagged.size >= 3
    flagged_t = (result.track.t_ns[flagged] - wheels.t_ns[0]) * 1e-9
    # a pose is compared over the second before it (window_s)
    assert np.all((flagged_t > 3.0) & (flagged_t < 5.6))
    assert result.counts['wheel_gross'] == flagged.size
    assert result.excluded['by_reason'] == {'wheel_gross': flagged.size}


def test_registering_every_second_scan_deskews_with_one_sweep_of_motion():
    sim = simulate(SimConfig(duration_s=8.0, seed=4, lidar=LIDAR))
    scans = list(sim.scans())
    every = register_frames(scans, ICP)
    strided = register_frames(scans, dataclasses.replace(ICP, stride=2))
    assert strided.status[1::2] == ('stride',) * len(strided.status[1::2])
    assert all(code == 'ok' for code in strided.status[0::2])
    result = lidar_ground_truth(scans, LIDAR.extrinsic(), dataclasses.replace(ICP, stride=2))
    assert len(result.track) == len(scans[0::2]) and result.track.valid.mean() > 0.95
    one_s = increment_errors(result.track, sim.pose_at, horizon_s=1.0)
    assert one_s.median_position_m < 0.03 and one_s.median_yaw_rad < 0.01
    assert every.registered.all()


def test_se3_power_scales_a_motion_in_time():
    motion = np.eye(4)
    motion[:2, :2] = [[math.cos(0.3), -math.sin(0.3)], [math.sin(0.3), math.cos(0.3)]]
    motion[:3, 3] = (0.5, 0.1, 0.02)
    half = se3_power(motion, 0.5)
    assert np.allclose(half @ half, motion)
    assert np.allclose(se3_power(motion, 1.0), motion)
    assert np.allclose(se3_power(motion, 0.0), np.eye(4))
    assert np.allclose(se3_power(motion, 2.0), motion @ motion)


def test_the_quality_measure_is_the_same_with_the_cheaper_tree(short_drive):
    """The unbalanced, uncompacted tree of the previous map points gives the same bits."""
    from scipy.spatial import cKDTree

    from skidkin_ros.adapters.lidar_quality import _world, registration_quality
    from skidkin_ros.adapters.lidar_register import _TREE

    sim, scans = short_drive
    pose = np.eye(4)
    pose[:2, :2] = [[math.cos(0.2), -math.sin(0.2)], [math.sin(0.2), math.cos(0.2)]]
    pose[:3, 3] = (0.4, -0.3, 0.01)
    measured = []
    for previous, current in zip(scans[:-1:5], scans[1::5]):
        world = _world(np.asarray(previous.xyz, dtype=float)[::3], pose)
        source = np.asarray(current.xyz, dtype=float)[::7]
        for tree in (cKDTree(world), cKDTree(world, **_TREE)):
            measured.append(registration_quality(source, pose, tree, 0.5, 400))
        assert measured[-1] == measured[-2]
        assert 0.0 < measured[-1][0] <= 1.0
    assert len(measured) >= 4


def test_se3_power_is_one_logarithm_and_a_scaled_exponential():
    """The loop takes one logarithm per frame for its two scaled motions: the same bits."""
    from skidkin_ros.core.rigid import se3_exp_scaled, se3_log

    motion = np.eye(4)
    motion[:2, :2] = [[math.cos(0.1), -math.sin(0.1)], [math.sin(0.1), math.cos(0.1)]]
    motion[:3, 3] = (0.12, 0.01, -0.003)
    twist = se3_log(motion)
    for fraction in (0.37, 1.0, 1.9):
        assert se3_exp_scaled(*twist, fraction).tobytes() == se3_power(motion, fraction).tobytes()
    assert np.allclose(se3_exp_scaled(*twist, 1.0), motion)


def test_hostile_points_leave_the_registration_byte_identical(short_drive):
    """NaN, inf, huge and overflowing points beside a scan: the same poses, and no warning."""
    import warnings

    from skidkin_ros.adapters.lidar_register import register_frames

    _, scans = short_drive
    bad = np.array([[np.nan, 1.0, 1.0], [np.inf, 0.0, 0.0], [-np.inf, np.nan, 2.0],
                    [1e300, 1e300, 0.0], [1e154, 1e154, 1e154], [3e153, 0.0, 0.0]])

    def frames(hostile):
        for scan in scans[:12]:
            xyz, times = np.asarray(scan.xyz, dtype=float), scan.t_rel_s
            if hostile:
                xyz = np.vstack([xyz, bad])
                times = np.concatenate([times, np.zeros(len(bad))])
            yield dataclasses.replace(scan, xyz=xyz, t_rel_s=times)

    clean = register_frames(frames(False), ICP)
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        dirty = register_frames(frames(True), dataclasses.replace(ICP, voxel_size_m=None))
        dirty_fixed = register_frames(frames(True), ICP)
    assert set(clean.status) == {'ok'} and dirty_fixed.status == clean.status
    assert dirty_fixed.lidar_pose.tobytes() == clean.lidar_pose.tobytes()
    assert set(dirty.status) == {'ok'}


def test_a_non_finite_icp_pose_is_one_dropped_frame_not_an_abort(short_drive, monkeypatch):
    """kiss-icp's ICP answering NaN once (injected: no recording here makes it) drops that frame.

    Before, the NaN pose went into kiss-icp's map, where Sophus aborts the process (SIGABRT).
    """
    from kiss_icp.registration import Registration

    from skidkin_ros.adapters.lidar_register import register_frames

    _, scans = short_drive
    frames = [dataclasses.replace(s, xyz=np.asarray(s.xyz, dtype=float)) for s in scans[:10]]
    clean = register_frames(frames, ICP)
    real, calls = Registration.align_points_to_map, []

    def align_nan_once(self, **kwargs):
        calls.append(1)
        return np.full((4, 4), np.nan) if len(calls) == 6 else real(self, **kwargs)

    monkeypatch.setattr(Registration, 'align_points_to_map', align_nan_once)
    faulty = register_frames(frames, ICP)
    assert faulty.status == clean.status[:5] + ('non_finite',) + clean.status[6:]
    assert np.all(np.isnan(faulty.lidar_pose[5])) and faulty.pose_t_ns[5] == -1
    assert np.array_equal(faulty.lidar_pose[:5], clean.lidar_pose[:5])
    # the frames after it register from the last good pose, near where they did without it
    assert np.all(np.isfinite(faulty.lidar_pose[6:]))
    assert np.max(np.abs(faulty.lidar_pose[6:, :3, 3] - clean.lidar_pose[6:, :3, 3])) < 0.05


def test_an_open_field_is_degenerate_and_flagged_by_icp_own_quality():
    sim = simulate(SimConfig(duration_s=4.0, seed=3, lidar=LidarConfig(azimuth_resolution_deg=1.0),
                             scene='forest'))
    field = dataclasses.replace(sim, scene=outdoor_scene(n_trees=0))
    forest = register_frames(list(sim.scans()), ICP)
    bare = register_frames(list(field.scans()), ICP)
    assert np.nanmin(forest.degeneracy) > 0.1  # structure all around the sensor
    assert np.nanmax(bare.degeneracy) == 0.0  # only ground: the planar position is free
    result = lidar_ground_truth(field.scans(), field.config.lidar.extrinsic(), ICP)
    # every pose after the first is excluded, most of them as degenerate
    assert not result.track.valid[1:].any()
    assert result.counts.get('icp_degenerate', 0) >= 0.8 * len(result.track)
