"""The ground truth of a bag in chunks, joined and cached, locally and on a Dask cluster.

Identical for any number of processes, cached per chunk (an interrupted run resumes), failures
named, and the same tasks on a Dask local cluster.

Real kiss-icp on real bags written by rosbags; recordings are short and chunks of 5 s.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from skidkin_ros.adapters.bag_reader import open_recording
from skidkin_ros.adapters.lidar_chunks import (bag_ground_truth, bag_identity, ChunkOptions,
                                               ChunkOutcome, join_chunks, plan_chunks,
                                               retry_cut_seams, run_chunks)
from skidkin_ros.adapters.lidar_gt import IcpConfig, lidar_ground_truth, Registration
from skidkin_ros.adapters.sim_writer import write_bag
from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.sim import LidarConfig, SimConfig, simulate
from skidkin_ros.sim.accuracy import increment_errors

LIDAR = LidarConfig(azimuth_resolution_deg=1.0, mount_xyz_m=(0.3, 0.1, 0.5), mount_yaw_rad=0.4)
ICP = IcpConfig(voxel_size_m=0.5, max_range_m=50.0)
CHUNKS = ChunkOptions(chunk_s=5.0, overlap_s=2.0)


@pytest.fixture(scope='module')
def drive(tmp_path_factory):
    sim = simulate(SimConfig(duration_s=16.0, seed=8, lidar=LIDAR, internal_rate_hz=200.0))
    bag, _ = write_bag(sim, tmp_path_factory.mktemp('chunks') / 'drive')
    return sim, bag


def ground_truth(bag, options=CHUNKS, cache_dir=None, **kwargs):
    with open_recording(bag) as rec:
        return bag_ground_truth(rec, bag, '/points', LIDAR.extrinsic(), ICP, options,
                                cache_dir=cache_dir, **kwargs)


def test_chunks_are_planned_with_a_warm_up_and_an_open_end(drive):
    _, bag = drive
    tasks = plan_chunks(str(bag), '/points', 10**9, 10**8, 159, 10**9, ICP, CHUNKS)
    assert [t.seam_ns for t in tasks] == [None, 6 * 10**9, 11 * 10**9]
    assert [t.start_ns for t in tasks] == [None, 4 * 10**9, 9 * 10**9]
    assert [t.stop_ns for t in tasks] == [6 * 10**9, 11 * 10**9, None]


def test_joined_chunks_equal_for_one_and_two_processes_and_as_accurate_as_one_run(drive):
    sim, bag = drive
    one = ground_truth(bag, dataclasses.replace(CHUNKS, jobs=1))
    two = ground_truth(bag, dataclasses.replace(CHUNKS, jobs=2))
    assert np.array_equal(one.track.t_ns, two.track.t_ns)
    assert np.array_equal(one.track.poses, two.track.poses)  # bit for bit
    assert np.array_equal(one.track.valid, two.track.valid)
    assert any('3 chunks' in note for note in one.notes)
    # every frame has one pose: the warm-up frames are not doubled
    with open_recording(bag) as rec:
        whole = lidar_ground_truth(rec.iter_lidar('/points'), LIDAR.extrinsic(), ICP)
    assert np.array_equal(one.track.t_ns, whole.track.t_ns)
    # the seams were tested and passed: increments across them are as good as in one run
    assert one.track.valid.all()
    chunked = increment_errors(one.track, sim.pose_at, horizon_m=2.0)
    single = increment_errors(whole.track, sim.pose_at, horizon_m=2.0)
    assert len(chunked) == len(single)
    assert chunked.median_position_m < 1.5 * single.median_position_m + 0.01
    p90 = np.percentile(chunked.position_m, 90), np.percentile(single.position_m, 90)
    assert p90[0] < 1.5 * p90[1] + 0.02


def test_the_cache_keeps_each_chunk_so_a_run_resumes_and_flags_are_recomputed(drive, tmp_path):
    sim, bag = drive
    cache = tmp_path / 'cache'
    wheels = sim.wheels  # the wheels also place the seams (lidar_calm): the same in every run
    first = ground_truth(bag, cache_dir=cache, wheels=wheels)
    assert not first.from_cache
    files = sorted(cache.glob('lidar_chunk_*.npz'))
    assert len(files) == 3
    files[1].unlink()  # as if the run had been interrupted before chunk 1 finished
    resumed = ground_truth(bag, cache_dir=cache, wheels=wheels)
    assert not resumed.from_cache
    assert any('2 of 3 chunk(s) read from the cache' in note for note in resumed.notes)
    assert np.array_equal(resumed.track.poses, first.track.poses)
    # only ICP is cached: new wheels give new flags from the same cached registration (these
    # turn as the real ones, so the seams stay, but say the robot drove 1 m/s faster after 8 s)
    faster = np.where((wheels.t_ns - wheels.t_ns[0]) > 8e9, 6.0, 0.0)
    lying = WheelSamples(wheels.t_ns, wheels.omega_l + faster, wheels.omega_r + faster)
    cached = ground_truth(bag, cache_dir=cache, wheels=lying)
    assert cached.from_cache
    assert cached.counts.get('wheel_gross', 0) > 0
    clean = ground_truth(bag, cache_dir=cache, wheels=wheels)
    assert clean.from_cache and clean.track.valid.all()
    # another ICP setting is another key; a corrupt file is recomputed, never fatal
    assert len(list(cache.glob('*.npz'))) == 3
    for path in cache.glob('*.npz'):
        path.write_bytes(b'not a cache')
    again = ground_truth(bag, cache_dir=cache, wheels=wheels)
    assert not again.from_cache
    assert np.array_equal(again.track.poses, first.track.poses)


def test_a_failed_chunk_is_named_and_the_others_are_kept(drive, caplog):
    _, bag = drive
    with open_recording(bag) as rec:
        first = next(iter(rec.iter_lidar('/points')))
    tasks = plan_chunks(str(bag), '/points', first.receive_ns, 10**8, 159, first.end_ns, ICP,
                        CHUNKS)
    broken = dataclasses.replace(tasks[1], bag=str(bag) + '_missing')
    with caplog.at_level(logging.WARNING):
        outcomes = run_chunks([tasks[0], broken, tasks[2]], CHUNKS)
    assert [o.error is None for o in outcomes] == [True, False, True]
    joined = join_chunks(outcomes, CHUNKS)
    assert any('chunk 1' in note and 'failed' in note and 'RecordingError' in note
               for note in joined.notes)
    assert len(joined.cut_frames) == 1  # chunk 2 starts behind a cut seam
    assert joined.registration.end_ns.size == len(outcomes[0].registration) + sum(
        np.count_nonzero(o.registration.receive_ns >= o.task.seam_ns) for o in outcomes[2:])
    truth = ground_truth(bag)  # the full run, for comparison of the kept chunks
    kept = np.isin(truth.track.t_ns, joined.registration.pose_t_ns)
    assert kept.sum() >= len(truth.track) - 60


def test_bag_identity_changes_with_the_bag(tmp_path):
    sim = simulate(SimConfig(duration_s=2.0, seed=6, lidar=LidarConfig(azimuth_resolution_deg=8)))
    bag, _ = write_bag(sim, tmp_path / 'a')
    first = bag_identity(bag)
    assert bag_identity(bag) == first
    storage = next(p for p in bag.iterdir() if p.suffix == '.db3')
    with open(storage, 'ab') as handle:
        handle.write(b'\0')
    assert bag_identity(bag) != first


def test_the_same_chunks_run_on_a_dask_local_cluster(drive):
    distributed = pytest.importorskip('distributed')
    _, bag = drive
    local = ground_truth(bag)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        remote = ground_truth(bag, dataclasses.replace(CHUNKS, cluster=cluster.scheduler_address))
    assert np.array_equal(remote.track.poses, local.track.poses)
    assert np.array_equal(remote.track.valid, local.track.valid)


def test_an_unreachable_cluster_is_a_clear_error(drive):
    pytest.importorskip('distributed')
    from skidkin_ros.errors import DataError
    _, bag = drive
    with pytest.raises(DataError, match='Dask scheduler'):
        ground_truth(bag, dataclasses.replace(CHUNKS, cluster='tcp://127.0.0.1:9'))


def _synthetic_outcome(task, scale=1.0):
    """Return a chunk that registered every frame of its window, driving along x at 1 m/s."""
    receive = np.arange(0, 25_000_000_000, 100_000_000, dtype=np.int64)
    inside = (receive >= (task.start_ns or 0)) & (receive < (task.stop_ns or receive[-1] + 1))
    t_s = receive[inside] * 1e-9
    poses = np.repeat(np.eye(4)[None], t_s.size, axis=0)
    poses[:, 0, 3] = (t_s - t_s[0]) * scale  # each chunk in the frame of its first cloud
    n = t_s.size
    reg = Registration(receive[inside], ('ok',) * n, receive[inside], poses, np.ones(n),
                       np.zeros(n), np.ones(n), receive[inside])
    return ChunkOutcome(task, reg)


def test_the_seam_note_counts_tested_and_untested_cuts_apart():
    # chunk 1 disagrees with chunk 0 (tested, cut); chunk 2 fails, so the seam before chunk 3
    # is cut untested; chunk 4 agrees with chunk 3 (tested, kept): 2 tested, 1 of them cut, 1
    # cut untested (before: '2 seam(s) tested, 2 cut', as if both tests had failed)
    tasks = plan_chunks('drive', '/points', 0, 10**8, 250, 0, ICP, CHUNKS)
    assert len(tasks) == 5
    outcomes = [_synthetic_outcome(tasks[0]), _synthetic_outcome(tasks[1], scale=1.5),
                ChunkOutcome(tasks[2], None, 'RecordingError: unreadable'),
                _synthetic_outcome(tasks[3]), _synthetic_outcome(tasks[4])]
    joined = join_chunks(outcomes, CHUNKS)
    assert len(joined.cut_frames) == 2
    assert (joined.seams_tested, joined.seams_failed, joined.seams_untested) == (2, 1, 1)
    assert joined.seams_cut == 2
    note = joined.seams_note(len(tasks), CHUNKS)
    assert '2 seam(s) tested, 1 of them cut; 1 cut untested (after a failed chunk' in note


def _bend(outcome, from_ns, to_ns, rad_per_frame=0.1):
    """Return the chunk as if it went wrong in [from, to): its poses turned more and more."""
    reg = outcome.registration
    poses = reg.lidar_pose.copy()
    rows = np.flatnonzero((reg.receive_ns >= from_ns) & (reg.receive_ns < to_ns))
    for k, row in enumerate(rows, start=1):
        c, s = np.cos(k * rad_per_frame), np.sin(k * rad_per_frame)
        turn = np.eye(4)
        turn[:2, :2] = [[c, -s], [s, c]]
        poses[row] = poses[row] @ turn
    return dataclasses.replace(outcome,
                               registration=dataclasses.replace(reg, lidar_pose=poses))


def _head(outcome):
    """Return the second before the chunk's seam, where the seam test looks."""
    return outcome.task.seam_ns - 10**9, outcome.task.seam_ns


def _tail(outcome):
    """Return the second before the chunk's end (the next chunk's seam)."""
    return outcome.task.stop_ns - 10**9, outcome.task.stop_ns


def test_c259_a_retry_that_breaks_the_next_seam_is_not_kept(drive):
    """A retried chunk replaces the first only where the join is no worse (its seam and the next).

    Real kiss-icp registrations of three 5 s chunks, each seam passing; chunk 1 is bent over
    the second before its seam (it started wrong: that seam fails) and its second try, a real
    registration from an earlier start, over the second before its end (it went wrong late).
    Kept, the retry would swap the cut seam 1 for a cut seam 2 and the note would say it
    joined (before: kept, '1 joined', chunk 2 cut).
    """
    _, bag = drive
    with open_recording(bag) as rec:
        first = next(iter(rec.iter_lidar('/points')))
    tasks = plan_chunks(str(bag), '/points', first.receive_ns, 10**8, 159, first.end_ns, ICP,
                        CHUNKS)
    runs = {jobs: run_chunks(tasks, dataclasses.replace(CHUNKS, jobs=jobs)) for jobs in (1, 2)}
    real = runs[1]
    assert join_chunks(real, CHUNKS).cut_frames == []

    def rerun_bending_chunk_1(jobs):
        def rerun(retry):
            again = run_chunks(retry, dataclasses.replace(CHUNKS, jobs=jobs))
            return [_bend(o, *_tail(o)) if o.task.index == 1 else o for o in again]
        return rerun

    started_wrong = [real[0], _bend(real[1], *_head(real[1])), real[2]]
    assert join_chunks(started_wrong, CHUNKS).failed_chunks == (1,)
    notes = []
    kept = retry_cut_seams(started_wrong, CHUNKS, rerun_bending_chunk_1(1), notes)
    assert kept[1] is started_wrong[1], notes
    joined = join_chunks(kept, CHUNKS)
    assert joined.failed_chunks == (1,) and joined.seams_cut == 1
    assert notes == ['1 cut seam(s) tried again with the chunk after it started 6 s before its '
                     'seam: 0 joined; 1 not kept (the seam after it would then fail)']
    # a retry that goes right is kept: both seams pass
    notes = []
    kept = retry_cut_seams(started_wrong, CHUNKS, lambda retry: run_chunks(retry, CHUNKS), notes)
    assert kept[1] is not started_wrong[1] and join_chunks(kept, CHUNKS).seams_cut == 0
    assert notes[0].endswith(': 1 joined'), notes
    # where the next seam failed already, the retry that mends its own seam is kept; the
    # same for one and two processes, byte for byte
    wrong_twice = [real[0], _bend(_bend(real[1], *_head(real[1])), *_tail(real[1])), real[2]]
    assert join_chunks(wrong_twice, CHUNKS).failed_chunks == (1, 2)
    results = {}
    for jobs in (1, 2):
        first_try = [runs[jobs][0],
                     _bend(_bend(runs[jobs][1], *_head(real[1])), *_tail(real[1])), runs[jobs][2]]
        notes = []
        kept = retry_cut_seams(first_try, CHUNKS, rerun_bending_chunk_1(jobs), notes)
        assert kept[1] is not first_try[1] and kept[2] is first_try[2], notes
        assert notes[0].endswith(': 1 joined'), notes
        results[jobs] = join_chunks(kept, CHUNKS)
        assert results[jobs].failed_chunks == (2,)
    assert np.array_equal(results[1].registration.lidar_pose, results[2].registration.lidar_pose)
    assert np.array_equal(results[1].registration.end_ns, results[2].registration.end_ns)
    assert results[1].cut_frames == results[2].cut_frames


_MAIN_PROBE = """
import sys
from concurrent.futures import ProcessPoolExecutor

from skidkin_ros.adapters import lidar_pool

if __name__ == '__main__':
    # a worker that reran this file has it as __main__ under the name __mp_main__
    probe = "__import__('sys').modules['__main__'].__name__ == '__mp_main__'"
    context = lidar_pool._pool_context()
    with ProcessPoolExecutor(1, mp_context=context) as executor:
        plain = executor.submit(eval, probe).result()
    main = sys.modules['__main__']
    with ProcessPoolExecutor(1, mp_context=context) as executor:
        with lidar_pool._bare_main():
            future = executor.submit(eval, probe)
        restored = sys.modules['__main__'] is main
        bare = future.result()
    print(plain, bare, restored)
"""


def test_pool_workers_do_not_rerun_the_parents_main_module(tmp_path):
    # A forkserver/spawn worker reruns the parent's main script (for `skidkin`: the whole CLI,
    # about 1.5 s of CPU) unless the pool starts under _bare_main; a chunk needs none of it.
    import os
    from pathlib import Path
    import subprocess
    import sys

    script = tmp_path / 'main_script.py'
    script.write_text(_MAIN_PROBE)
    root = str(Path(__file__).resolve().parents[1])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [root, *filter(None, [os.environ.get('PYTHONPATH')])]))
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          env=env, timeout=120, check=True)
    assert done.stdout.split() == ['True', 'False', 'True']


_PRELOAD_PROBE = """
from concurrent.futures import ProcessPoolExecutor

from skidkin_ros.adapters import lidar_pool

if __name__ == '__main__':
    probe = "[m in __import__('sys').modules for m in %r]" % (lidar_pool._WORKER_MODULES,)
    with lidar_pool._bare_main():
        with ProcessPoolExecutor(2, mp_context=lidar_pool._pool_context()) as executor:
            first = executor.submit(eval, probe)
    print(all(first.result()))
"""


def test_pool_workers_start_with_what_a_chunk_imports(tmp_path):
    # The forkserver imports the chunk's modules (kiss-icp, the bag reader: about 0.5 s of CPU)
    # once; a worker forked from it has them before its first task instead of importing them.
    import multiprocessing
    import os
    from pathlib import Path
    import subprocess
    import sys

    if 'forkserver' not in multiprocessing.get_all_start_methods():
        pytest.skip('no forkserver on this platform')
    script = tmp_path / 'preload_script.py'
    script.write_text(_PRELOAD_PROBE)
    root = str(Path(__file__).resolve().parents[1])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [root, *filter(None, [os.environ.get('PYTHONPATH')])]))
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          env=env, timeout=120, check=True)
    assert done.stdout.split() == ['True']
