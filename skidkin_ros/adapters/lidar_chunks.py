"""Lidar ground truth of a recording in independent, overlapping time chunks, cached per chunk.

The calibrator uses ground-truth increments over 2 m segments and never a globally consistent
map, so a long recording can be registered in pieces, each from scratch, on as many cores or
machines as there are. Recipe (:func:`bag_ground_truth`):

1. **Plan** (:func:`plan_chunks`): seams every ``chunk_s`` of bag time from the first cloud,
   each moved (within a quarter chunk) to where the wheels turn least over its warm-up
   (:mod:`~skidkin_ros.adapters.lidar_calm`; without wheels, where they are). Chunk k
   registers from ``overlap_s`` before its seam (a warm-up: kiss-icp's map and motion model are
   empty at the start) to the next seam; the last chunk is open-ended.
2. **Run**: each chunk is one task, :func:`run_chunk`, that opens the recording itself. Tasks
   run on ``jobs`` local processes (forkserver; ``jobs`` 1: here), or on a Dask cluster when a
   scheduler address is given. kiss-icp runs with one thread in every chunk, so a chunk's
   result depends on nothing but the recording and the settings: the joined ground truth is
   the same for any number of processes, on any machine.
3. **Cache**: every finished chunk's registration is written at once (npz keyed by the
   recording's identity, the topic, the chunk's window, the ICP settings and the kiss-icp
   version). An interrupted run resumes with the chunks it lacks. Flags are not cached: the
   guard (lidar_guard) runs on every call, on the wheels, IMU and limits given then.
4. **Join** (:func:`join_chunks`), using the overlap: chunk k's poses are composed onto chunk
   k-1's at the last frame both registered before the seam (the anchor), and chunk k's
   warm-up frames are dropped. An increment across a seam is then the product of two ICP
   increments, each from a warmed-up map, and never compares two unrelated frames. Before a
   seam is used it is tested: over the last ``overlap_s / 2`` before the anchor, both chunks
   registered the same frames, and their motions must agree (``seam_abs_m`` + 10 % in
   translation, ``seam_abs_rad`` + 10 % in rotation: loose enough for two registrations' own
   noise, a few cm per frame on sparse outdoor scans, tight enough for a chunk that started
   wrong). A seam that fails, or has no common frame, is cut: the first pose after it is
   flagged 'seam', so no segment crosses it. Before it is cut, the chunk after it is registered
   once more from an earlier start (:func:`retry_cut_seams`: a warm-up three times as long),
   and that registration is kept where its seam then passes and the next seam does not newly
   fail.
5. **Failures**: a chunk whose task fails (an unreadable part of the recording, a worker that
   died) is named in the notes and its frames get no ground truth; the other chunks are kept,
   and the chunk after it starts behind a cut seam. When every chunk fails, DataError.

Where each step lives: planning and the types in :mod:`~skidkin_ros.adapters.lidar_plan`,
running in :mod:`~skidkin_ros.adapters.lidar_pool`, the cache in
:mod:`~skidkin_ros.adapters.lidar_cache`, joining in :mod:`~skidkin_ros.adapters.lidar_seams`;
this module wires them with the self-check (:func:`bag_ground_truth`) and re-exports their API.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import os
from pathlib import Path
from typing import Any, Callable, Union

import numpy as np

from skidkin_ros.adapters.icp_selfcheck import (check_samples, finer_than_reference,
                                                is_automatic, plan_samples, reference_config,
                                                SelfCheckOptions)
from skidkin_ros.adapters.lidar_cache import bag_identity, CACHE_VERSION, chunk_key  # noqa: F401
from skidkin_ros.adapters.lidar_calm import (calm_seams, calm_windows, nominal_seams,
                                             seams_placed_note)
from skidkin_ros.adapters.lidar_gt import GroundTruth, guarded_truth, IcpConfig
from skidkin_ros.adapters.lidar_plan import (ChunkOptions, ChunkOutcome, ChunkTask,  # noqa: F401
                                             plan_chunks)
from skidkin_ros.adapters.lidar_pool import Progress, run_chunk, run_chunks  # noqa: F401
from skidkin_ros.adapters.lidar_seams import join_chunks, Joined  # noqa: F401
from skidkin_ros.core.drive import ImuSamples, WheelSamples
from skidkin_ros.core.timeunits import NS_PER_S, s_to_ns

__all__ = ['CACHE_VERSION', 'ChunkOptions', 'ChunkTask', 'bag_identity', 'bag_ground_truth',
           'join_chunks', 'plan_chunks', 'retry_cut_seams', 'run_chunk']

# Frames read to learn the lidar's period before planning.
_PERIOD_FRAMES = 11
# Task indices of the self-check's sample windows (chunk indices stay below).
_SAMPLE_INDEX = 100_000


def bag_ground_truth(rec: Any, path: Union[str, os.PathLike], topic: str,
                     extrinsic: np.ndarray, config: IcpConfig | None = None,
                     options: ChunkOptions | None = None, *, limits: Any = None,
                     wheels: WheelSamples | None = None, imu: ImuSamples | None = None,
                     cache_dir: Union[str, os.PathLike, None] = None,
                     on_progress: Progress | None = None,
                     check: SelfCheckOptions | None = None) -> GroundTruth:
    """Return the lidar ground truth of a recording, registered in chunks (module docstring).

    ``rec``: the open BagRecording of ``path`` (used to plan: the first clouds and the count);
    ``wheels`` / ``imu``: for the guard; ``cache_dir``: where chunk registrations are kept
    (None: no cache); ``on_progress(frames done, frames total)``; ``check``: the self-check of
    the fast kiss-icp settings (:mod:`skidkin_ros.adapters.icp_selfcheck`; None: its defaults).
    """
    from skidkin_ros.errors import RecordingError

    config = config or IcpConfig()
    options = options or ChunkOptions()
    check = check or SelfCheckOptions()
    first = []
    for frame in rec.iter_lidar(topic):
        first.append(frame)
        if len(first) >= _PERIOD_FRAMES:
            break
    if not first:
        raise RecordingError(f'{path}: lidar topic {topic} holds no usable cloud')
    automatic = is_automatic(config)
    config = config.with_voxel_for(first[0].xyz)
    ends = np.array([f.end_ns for f in first], dtype=np.int64)
    period_ns = max(int(np.median(np.diff(ends))) if ends.size > 1 else 100_000_000, 1)
    n_frames = sum(s.count for s in rec.summary(time_ranges=False) if s.topic == topic)
    first_receive = int(first[0].receive_ns)
    span_ns = max(n_frames - 1, 0) * period_ns
    nominal = nominal_seams(first_receive, period_ns, n_frames, s_to_ns(options.chunk_s))
    seams = calm_seams(nominal, wheels, s_to_ns(options.overlap_s), s_to_ns(options.chunk_s),
                       period_ns, first_receive + span_ns)
    plan = _Plan(str(path), topic, first_receive, period_ns, n_frames, int(first[0].end_ns),
                 options, tuple(seams))
    tasks = plan.tasks(config)
    samples: list[tuple[tuple[int, int | None], ChunkTask]] = []
    reference = reference_config(config)
    notes: list[str] = []
    if check.enabled and automatic and finer_than_reference(config, reference):
        notes.append(f'kiss-icp settings: the voxel from the data ({config.voxel_size_m:g} m) is '
                     f"finer than kiss-icp's ({reference.voxel_size_m:g} m), where the fast "
                     "settings are not faster: kiss-icp's defaults are used")
        config = replace(reference, stride=config.stride)
        tasks = plan.tasks(config)
    if config.stride > 1:
        # one scan in K is a rung of the check too: the reference registers every scan
        reference = replace(reference, stride=1)
    if (check.enabled and automatic and reference != config
            and span_ns >= (check.window_s + check.warmup_s) * NS_PER_S):
        windows = plan_samples([t.stop_ns for t in tasks], first_receive, first_receive + span_ns,
                               check)
        windows = calm_windows(windows, wheels, s_to_ns(check.window_s + check.warmup_s),
                               s_to_ns(check.warmup_s), period_ns, first_receive)
        grid = tasks[0].grid if reference.stride > 1 else None
        samples = [(window, ChunkTask(str(path), topic, _SAMPLE_INDEX + k, window[0],
                                      window[1], None, reference, grid))
                   for k, window in enumerate(windows)]
    identity = bag_identity(path) if cache_dir is not None else None
    cache = None if cache_dir is None else Path(cache_dir)
    sample_frames = sum(int((check.window_s + check.warmup_s) * NS_PER_S / period_ns)
                        for _ in samples)
    outcomes = run_chunks(tasks + [task for _, task in samples], options, cache_dir=cache,
                          identity=identity, total_frames=plan.frames(len(tasks)) + sample_frames,
                          on_progress=on_progress)
    outcomes, sampled = outcomes[:len(tasks)], outcomes[len(tasks):]

    def rerun(retry: list[ChunkTask]) -> list[ChunkOutcome]:
        return run_chunks(retry, options, cache_dir=cache, identity=identity,
                          total_frames=sum(plan.retry_frames(t) for t in retry),
                          on_progress=on_progress)

    retry_notes: list[str] = []
    outcomes = retry_cut_seams(outcomes, options, rerun, retry_notes)
    if samples:
        choice = check_samples([o.registration for o in outcomes],
                               [(window, o.registration) for (window, _), o in
                                zip(samples, sampled)], config, reference, check)
        notes.append(choice.note())
        if not choice.kept_fast:
            config = choice.config
            tasks = plan.tasks(config)
            outcomes = run_chunks(tasks, options, cache_dir=cache, identity=identity,
                                  total_frames=plan.frames(len(tasks)), on_progress=on_progress)
            retry_notes.clear()
            outcomes = retry_cut_seams(outcomes, options, rerun, retry_notes)
    elif check.enabled and not notes:
        notes.append('kiss-icp settings not self-checked: ' + (
            'they were set explicitly' if not automatic or reference == config
            else 'the recording is shorter than one sample window'))
    joined = join_chunks(outcomes, options)
    notes = list(dict.fromkeys(joined.notes)) + notes
    if len(tasks) > 1:
        notes.append(joined.seams_note(len(tasks), options))
        notes.append(seams_placed_note(nominal, seams, first_receive, wheels))
        notes.extend(retry_notes)
    cached = sum(1 for o in outcomes if o.cached)
    if cached:
        notes.append(f'ground truth: {cached} of {len(tasks)} chunk(s) read from the cache '
                     f'{cache_dir}')
    return guarded_truth(joined.registration, extrinsic, config, limits, wheels=wheels, imu=imu,
                         seams=joined.cut_frames, from_cache=cached == len(tasks), notes=notes)


@dataclass(frozen=True)
class _Plan:
    """What planning the chunks of one recording needs, to plan them for any settings."""

    bag: str
    topic: str
    first_receive_ns: int
    period_ns: int
    n_frames: int
    first_end_ns: int
    options: ChunkOptions
    seams_ns: tuple[int, ...]

    def tasks(self, config: IcpConfig) -> list[ChunkTask]:
        return plan_chunks(self.bag, self.topic, self.first_receive_ns, self.period_ns,
                           self.n_frames, self.first_end_ns, config, self.options,
                           self.seams_ns)

    def retry_frames(self, task: ChunkTask) -> int:
        """Return about how many frames a retried chunk reads (its window; open: a chunk)."""
        span = (s_to_ns(self.options.chunk_s) if task.stop_ns is None or task.start_ns is None
                else task.stop_ns - task.start_ns)
        return int(span // self.period_ns)

    def frames(self, n_tasks: int) -> int:
        """Return the frames all chunks read: the recording and every warm-up."""
        warmup = int(self.options.overlap_s * NS_PER_S / self.period_ns)
        return self.n_frames + warmup * (n_tasks - 1)


# A chunk after a cut seam is registered again with a warm-up this many times as long.
_RETRY_WARMUPS = 3


def retry_cut_seams(outcomes: list[ChunkOutcome], options: ChunkOptions,
                    rerun: Callable[[list[ChunkTask]], list[ChunkOutcome]],
                    notes: list[str]) -> list[ChunkOutcome]:
    """Register the chunk after each seam that failed its test again from an earlier start.

    A chunk that started where its registration went wrong (a spin the wheels did not show, a
    scan the map could not hold) gets a warm-up ``_RETRY_WARMUPS`` times as long, same seam and
    end; its new registration replaces the old one only where the join is then no worse: its
    seam passes, and the seam after it passes or had failed already. The rule reads the
    registrations only, so it is the same for any number of processes.
    """
    joined = join_chunks(outcomes, options)
    if not joined.failed_chunks:
        return outcomes
    overlap_ns = s_to_ns(options.overlap_s)
    retry = [replace(outcomes[i].task, start_ns=int(outcomes[i].task.seam_ns)
                     - _RETRY_WARMUPS * overlap_ns)
             for i in joined.failed_chunks if outcomes[i].task.seam_ns is not None]
    kept = list(outcomes)
    for outcome in rerun(retry):
        if outcome.registration is not None:
            kept[outcome.task.index] = outcome
    tried = sorted(t.index for t in retry if kept[t.index] is not outcomes[t.index])
    refused = 0
    while True:
        worse = _worse_retry(tried, kept, outcomes, joined, join_chunks(kept, options))
        if not worse:
            break
        index, next_seam = worse
        kept[index] = outcomes[index]
        refused += int(next_seam)
    joined_again = sum(1 for i in tried if kept[i] is not outcomes[i])
    note = (f'{len(retry)} cut seam(s) tried again with the chunk after it started '
            f'{_RETRY_WARMUPS * options.overlap_s:g} s before its seam: {joined_again} joined')
    if refused:
        note += f'; {refused} not kept (the seam after it would then fail)'
    notes.append(note)
    return kept


def _worse_retry(tried: list[int], kept: list[ChunkOutcome], outcomes: list[ChunkOutcome],
                 first: Joined, now: Joined) -> tuple[int, bool] | None:
    """Return the first kept retry that leaves the join worse, and whether by the next seam.

    A retry stays where its own seam passes and the seam after it passes, or had failed
    already (without it); otherwise it would only swap one cut for another.
    """
    for index in tried:
        if kept[index] is outcomes[index]:
            continue
        if index in now.cut_chunks:
            return index, False
        if index + 1 in now.cut_chunks and index + 1 not in first.cut_chunks:
            return index, True
    return None
