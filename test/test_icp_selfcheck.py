"""The self-check of the fast kiss-icp settings: sample windows, motion comparison, choice.

Unit facts on synthetic registrations (identical motions agree, a slid registration does not),
then real kiss-icp on a real bag: the check runs with the chunks, its choice is the same for any
number of processes, and a check that cannot pass registers the recording with kiss-icp's
defaults, bit for bit as a run given those settings.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from skidkin_ros.adapters.bag_reader import open_recording
from skidkin_ros.adapters.icp_selfcheck import (check_samples, compare_motion,
                                                finer_than_reference, is_automatic,
                                                plan_samples, reference_config,
                                                SelfCheckOptions)
from skidkin_ros.adapters.lidar_chunks import bag_ground_truth, ChunkOptions
from skidkin_ros.adapters.lidar_gt import IcpConfig, Registration
from skidkin_ros.adapters.sim_writer import write_bag
from skidkin_ros.errors import ParameterError
from skidkin_ros.sim import LidarConfig, SimConfig, simulate

LIDAR = LidarConfig(azimuth_resolution_deg=1.0, mount_xyz_m=(0.3, 0.1, 0.5), mount_yaw_rad=0.4)
CHUNKS = ChunkOptions(chunk_s=6.0, overlap_s=2.0)
CHECK = SelfCheckOptions(windows=2, window_s=4.0, warmup_s=1.0)


def _straight(n=60, speed_m=0.05, slide_from=None, slide_m=0.0, period_ns=10**8):
    """Return a registration driving straight along x, sliding by slide_m per frame later."""
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    x = np.arange(n) * speed_m
    if slide_from is not None:
        x[slide_from:] += np.arange(n - slide_from) * slide_m
    poses[:, 0, 3] = x
    ends = 10**9 + np.arange(n, dtype=np.int64) * period_ns
    nan = np.full(n, np.nan)
    return Registration(ends, ('ok',) * n, ends.copy(), poses, nan, nan, nan)


def test_identical_motions_agree_and_a_slid_registration_does_not():
    reference = _straight()
    window = (10**9, None)
    same = compare_motion(_straight(), reference, window, CHECK)
    assert same.compared > 0 and same.agreeing == same.compared and same.worst_m == 0.0
    # a different start frame does not matter: only motions are compared
    shifted = _straight()
    shifted.lidar_pose[:, 1, 3] += 3.0
    assert compare_motion(shifted, reference, window, CHECK).share == 1.0
    slid = compare_motion(_straight(slide_from=20, slide_m=0.03), reference, window, CHECK)
    assert slid.share < CHECK.min_agree
    fast, ref = IcpConfig(voxel_size_m=1.4), reference_config(IcpConfig(voxel_size_m=1.4))
    keep = check_samples([_straight()], [(window, reference)], fast, ref, CHECK)
    assert keep.kept_fast and keep.config == fast and 'kept' in keep.note()
    drop = check_samples([_straight(slide_from=20, slide_m=0.03)], [(window, reference)], fast,
                         ref, CHECK)
    assert not drop.kept_fast and drop.config == ref and 'disagree' in drop.note()
    none = check_samples([None], [(window, reference)], fast, ref, CHECK)
    assert none.kept_fast and 'not self-checked' in none.note()


def test_the_reference_is_kiss_icps_defaults_and_only_automatic_settings_are_checked():
    ref = reference_config(IcpConfig(max_range_m=60.0, voxel_size_m=1.4, stride=2))
    assert (ref.voxel_size_m, ref.convergence, ref.max_points_per_voxel) == (0.6, 1e-4, 20)
    assert ref.stride == 2 and ref.max_range_m == 60.0
    assert is_automatic(IcpConfig())
    assert not is_automatic(IcpConfig(voxel_size_m=0.5))
    assert not is_automatic(IcpConfig(convergence=1e-4))
    with pytest.raises(ParameterError, match='horizon_s'):
        SelfCheckOptions(window_s=1.0, horizon_s=1.0)


def test_sample_windows_end_where_chunks_end_the_open_last_one_included():
    options = SelfCheckOptions(windows=2, window_s=8.0, warmup_s=2.0)
    windows = plan_samples([60 * 10**9, 120 * 10**9, None], 0, 200 * 10**9, options)
    assert windows == [(50 * 10**9, 60 * 10**9), (190 * 10**9, None)]
    # one window per 100 s recorded, at least one
    assert len(plan_samples([60 * 10**9, 120 * 10**9, None], 0, 150 * 10**9, options)) == 1
    assert len(plan_samples([None], 0, 30 * 10**9, options)) == 1


@pytest.fixture(scope='module')
def drive(tmp_path_factory):
    sim = simulate(SimConfig(duration_s=14.0, seed=8, lidar=LIDAR, internal_rate_hz=200.0))
    bag, _ = write_bag(sim, tmp_path_factory.mktemp('selfcheck') / 'drive')
    return sim, bag


def _truth(bag, icp, options=CHUNKS, check=CHECK):
    with open_recording(bag) as rec:
        return bag_ground_truth(rec, bag, '/points', LIDAR.extrinsic(), icp, options,
                                check=check)


@pytest.mark.heavy
def test_the_check_runs_with_the_chunks_and_gives_the_same_poses_for_one_and_two_processes(
        drive):
    _, bag = drive
    icp = IcpConfig(max_range_m=50.0)
    one = _truth(bag, icp, dataclasses.replace(CHUNKS, jobs=1))
    two = _truth(bag, icp, dataclasses.replace(CHUNKS, jobs=2))
    assert np.array_equal(one.track.poses, two.track.poses)  # bit for bit
    assert np.array_equal(one.track.valid, two.track.valid)
    checked = [n for n in one.notes if n.startswith('kiss-icp settings self-check')]
    assert len(checked) == 1 and checked == [n for n in two.notes if n in checked]


@pytest.mark.heavy
def test_a_check_that_cannot_pass_registers_with_kiss_icps_defaults(drive):
    _, bag = drive
    icp = IcpConfig(max_range_m=50.0)
    strict = dataclasses.replace(CHECK, abs_m=1e-9, abs_rad=1e-9, rel=0.0)
    chosen = _truth(bag, icp, check=strict)
    assert any('disagree' in n for n in chosen.notes)
    with open_recording(bag) as rec:
        first = next(iter(rec.iter_lidar('/points')))
    reference = reference_config(icp.with_voxel_for(first.xyz))
    direct = _truth(bag, reference, check=strict)
    assert chosen.config.voxel_size_m == reference.voxel_size_m
    assert np.array_equal(chosen.track.poses, direct.track.poses)
    assert any('set explicitly' in n for n in direct.notes)
    off = _truth(bag, icp, check=SelfCheckOptions(enabled=False))
    assert not any('self-check' in n or 'self-checked' in n for n in off.notes)


def test_one_jump_is_enough_to_drop_the_fast_settings():
    reference = _straight(n=100)
    jumped = _straight(n=100)
    jumped.lidar_pose[50:, 0, 3] += 0.8  # one 0.8 m jump, the rest identical
    agreement = compare_motion(jumped, reference, (10**9, None), CHECK)
    assert agreement.share >= CHECK.min_agree and agreement.worst_m > CHECK.gross_m
    choice = check_samples([jumped], [((10**9, None), reference)], IcpConfig(voxel_size_m=1.4),
                           reference_config(IcpConfig(voxel_size_m=1.4)), CHECK)
    assert not choice.kept_fast


def test_a_voxel_finer_than_kiss_icps_means_kiss_icps_defaults():
    reference = reference_config(IcpConfig(voxel_size_m=0.55))
    assert finer_than_reference(IcpConfig(voxel_size_m=0.55), reference)
    assert not finer_than_reference(IcpConfig(voxel_size_m=1.4), reference)
    assert not finer_than_reference(IcpConfig(), reference_config(IcpConfig()))


def test_one_scan_in_two_is_compared_with_every_scan():
    # the full-rate reference registers every scan; the strided one every other: the motions
    # are compared on the scans both registered
    every = _straight(n=100)
    strided = _straight(n=100)
    strided = dataclasses.replace(strided, status=tuple('ok' if i % 2 == 0 else 'stride'
                                                        for i in range(100)))
    agreement = compare_motion(strided, every, (10**9, None), CHECK)
    assert agreement.compared > 0 and agreement.share == 1.0
    slid = _straight(n=100, slide_from=50, slide_m=0.05)
    slid = dataclasses.replace(slid, status=strided.status)
    assert compare_motion(slid, every, (10**9, None), CHECK).share < CHECK.min_agree


@pytest.mark.heavy
def test_one_scan_in_two_is_checked_against_every_scan_and_dropped_when_it_disagrees(drive):
    # C220: --stride K is a rung of the self-check: its sample registers every scan; kept when
    # the 1 s motions agree, else every scan with kiss-icp's defaults; same poses for any jobs
    _, bag = drive
    icp = IcpConfig(max_range_m=50.0, stride=2)
    one = _truth(bag, icp, dataclasses.replace(CHUNKS, jobs=1))
    two = _truth(bag, icp, dataclasses.replace(CHUNKS, jobs=2))
    assert np.array_equal(one.track.poses, two.track.poses)  # bit for bit
    checked = [n for n in one.notes if n.startswith('kiss-icp settings self-check')]
    assert len(checked) == 1 and 'one scan in 2' in checked[0] and 'kept' in checked[0]
    assert one.config.stride == 2 and one.counts.get('stride', 0) > 0
    strict = dataclasses.replace(CHECK, abs_m=1e-9, abs_rad=1e-9, rel=0.0)
    dropped = _truth(bag, icp, check=strict)
    assert any('disagree' in n and 'every scan' in n for n in dropped.notes)
    assert dropped.config.stride == 1 and not dropped.counts.get('stride')
    with open_recording(bag) as rec:
        first = next(iter(rec.iter_lidar('/points')))
    reference = reference_config(IcpConfig(max_range_m=50.0).with_voxel_for(first.xyz))
    direct = _truth(bag, reference, check=strict)
    assert np.array_equal(dropped.track.poses, direct.track.poses)
