"""Lidar ground truth of a recording in independent, overlapping time chunks, cached per chunk.

The calibrator uses ground-truth increments over 2 m segments and never a globally consistent
map, so a long recording can be registered in pieces, each from scratch, on as many cores or
machines as there are. Recipe (:func:`bag_ground_truth`):

1. **Plan** (:func:`plan_chunks`): seams every ``chunk_s`` of bag time from the first cloud.
   Chunk k registers from ``overlap_s`` before its seam (a warm-up: kiss-icp's map and motion
   model are empty at the start) to the next seam; the last chunk is open-ended.
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
   flagged 'seam', so no segment crosses it.
5. **Failures**: a chunk whose task fails (an unreadable part of the recording, a worker that
   died) is named in the notes and its frames get no ground truth; the other chunks are kept,
   and the chunk after it starts behind a cut seam. When every chunk fails, DataError.
"""

from __future__ import annotations

from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
import contextlib
from dataclasses import dataclass, field
import hashlib
import io
import json
import logging
import math
import multiprocessing
import os
from pathlib import Path
import signal
import sys
import types
from typing import Any, Callable, Iterator, Mapping, Sequence, Union

import numpy as np

from skidkin_ros.adapters import cluster
from skidkin_ros.adapters.icp_selfcheck import (check_samples, finer_than_reference,
                                                is_automatic, plan_samples, reference_config,
                                                SelfCheckOptions)
from skidkin_ros.adapters.lidar_gt import (FrameGrid, GroundTruth, guarded_truth, IcpConfig,
                                           register_frames, Registration)
from skidkin_ros.atomic import atomic_write_bytes
from skidkin_ros.core.drive import ImuSamples, WheelSamples
from skidkin_ros.core.timeunits import NS_PER_S, s_to_ns
from skidkin_ros.errors import DataError, OutputError, ParameterError

__all__ = ['CACHE_VERSION', 'ChunkOptions', 'ChunkTask', 'bag_identity', 'bag_ground_truth',
           'join_chunks', 'plan_chunks', 'run_chunk']

_LOG = logging.getLogger(__name__)
CACHE_VERSION = 2
Progress = Callable[[int, int], None]
# Frames between two progress messages of a worker.
_PROGRESS_EVERY = 10
# Frames read to learn the lidar's period before planning.
_PERIOD_FRAMES = 11
# Task indices of the self-check's sample windows (chunk indices stay below).
_SAMPLE_INDEX = 100_000


@dataclass(frozen=True)
class ChunkOptions:
    """How to cut and where to run: chunk length and overlap (s), processes, Dask scheduler.

    ``jobs``: local processes (1: in this process); ``cluster``: a Dask scheduler address
    (``tcp://host:8786``; the workers need skidkin_ros and the recording at the same path);
    ``seam_abs_m`` / ``seam_abs_rad``: the seam test's tolerances.
    """

    chunk_s: float = 60.0
    overlap_s: float = 4.0
    jobs: int = 1
    cluster: str | None = None
    seam_abs_m: float = 0.25
    seam_abs_rad: float = 0.05

    def __post_init__(self) -> None:
        if not self.chunk_s >= 5.0:
            raise ParameterError(f'chunk length must be >= 5 s, got {self.chunk_s}')
        if not 0.5 <= self.overlap_s <= self.chunk_s / 2:
            raise ParameterError('chunk overlap must be between 0.5 s and half the chunk '
                                 f'length, got {self.overlap_s} s for chunks of {self.chunk_s} s')
        if not isinstance(self.jobs, int) or self.jobs < 1:
            raise ParameterError(f'jobs must be a whole number >= 1, got {self.jobs!r}')
        if self.seam_abs_m <= 0 or self.seam_abs_rad <= 0:
            raise ParameterError('seam tolerances must be > 0')


@dataclass(frozen=True)
class ChunkTask:
    """One chunk: the recording, the lidar topic and the bag-time window to register.

    ``start_ns`` / ``stop_ns``: receive-time window ([start, stop), None: open); ``seam_ns``:
    where the chunk's own part begins (its frames before it are the warm-up; None: chunk 0).
    """

    bag: str
    topic: str
    index: int
    start_ns: int | None
    stop_ns: int | None
    seam_ns: int | None
    config: IcpConfig
    grid: FrameGrid | None = None


@dataclass
class ChunkOutcome:
    """What one chunk gave: its registration, or why it failed; read from the cache or not."""

    task: ChunkTask
    registration: Registration | None = None
    error: str | None = None
    notes: list[str] = field(default_factory=list)
    cached: bool = False


def bag_identity(path: Union[str, os.PathLike]) -> dict[str, Any]:
    """Return what identifies a recording for the cache: resolved path, sizes, mtimes, metadata.

    A bag folder contributes the hash of its metadata.yaml and the size and mtime of each storage
    file; a single file its size and mtime.
    """
    target = Path(path).resolve()
    if not target.exists():
        raise DataError(f'cannot identify recording {target}: it does not exist')
    files = sorted(p for p in target.iterdir() if p.is_file()) if target.is_dir() else [target]
    entries = []
    for item in files:
        stat = item.stat()
        entry = {'name': item.name, 'size': stat.st_size, 'mtime_ns': stat.st_mtime_ns}
        if item.name == 'metadata.yaml':
            entry['sha256'] = hashlib.sha256(item.read_bytes()).hexdigest()
        entries.append(entry)
    return {'path': str(target), 'files': entries}


def plan_chunks(bag: str, topic: str, first_receive_ns: int, period_ns: int, n_frames: int,
                first_end_ns: int, config: IcpConfig, options: ChunkOptions) -> list[ChunkTask]:
    """Cut the recording's lidar into chunks (see the module docstring, step 1).

    The number of chunks comes from the frame count and period; the last chunk is open-ended,
    so nothing is lost when the estimate is short.
    """
    chunk_ns = s_to_ns(options.chunk_s)
    overlap_ns = s_to_ns(options.overlap_s)
    span_ns = max(int(n_frames), 1) * max(int(period_ns), 1)
    count = max(1, int(math.ceil(span_ns / chunk_ns - 0.25)))
    grid = (FrameGrid.for_frames(first_end_ns, period_ns, config.stride)
            if config.stride > 1 else None)
    tasks = []
    for k in range(count):
        seam = first_receive_ns + k * chunk_ns if k else None
        start = seam - overlap_ns if seam is not None else None
        stop = first_receive_ns + (k + 1) * chunk_ns if k < count - 1 else None
        tasks.append(ChunkTask(str(bag), topic, k, start, stop, seam, config, grid))
    return tasks


# -- one chunk, wherever it runs ----------------------------------------------------------------
_PROGRESS_QUEUE: Any = None


def _init_worker(queue: Any) -> None:
    """Set up a worker process: progress queue, default SIGTERM, Ctrl-C left to the parent."""
    global _PROGRESS_QUEUE
    _PROGRESS_QUEUE = queue
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def run_chunk(task: ChunkTask, on_frame: Callable[[int], None] | None = None
              ) -> dict[str, Any]:
    """Register one chunk of a recording from scratch; return plain arrays and notes.

    Runs anywhere the recording is readable at ``task.bag`` (a worker process, a Dask worker);
    the result is what :class:`Registration.from_arrays` reads, plus ``notes``.
    """
    from skidkin_ros.adapters.bag_reader import open_recording

    if on_frame is None and _PROGRESS_QUEUE is not None:
        queue = _PROGRESS_QUEUE

        def on_frame(n: int) -> None:
            if n % _PROGRESS_EVERY == 0:
                queue.put((task.index, n))
    with open_recording(task.bag) as rec:
        frames = rec.iter_lidar(task.topic, start_ns=task.start_ns, stop_ns=task.stop_ns)
        registration = register_frames(frames, task.config, grid=task.grid, on_frame=on_frame)
        notes = list(rec.notes)
    out: dict[str, Any] = registration.to_arrays()
    out['notes'] = notes
    return out


# -- cache -------------------------------------------------------------------------------------
def _kiss_version() -> str:
    try:
        from importlib.metadata import version
        return version('kiss-icp')
    except Exception:  # noqa: B902 - any failure: the key just says so
        return 'unknown'


def chunk_key(task: ChunkTask, identity: Mapping[str, Any]) -> str:
    """Return the cache key of a chunk: everything its registration depends on."""
    payload = {'version': CACHE_VERSION, 'kiss_icp': _kiss_version(), 'bag': identity,
               'topic': task.topic, 'window': [task.start_ns, task.stop_ns],
               'config': task.config.as_dict(),
               'grid': None if task.grid is None else [task.grid.origin_ns, task.grid.cell_ns]}
    text = json.dumps(payload, sort_keys=True, default=str)
    return hashlib.sha256(text.encode('utf-8')).hexdigest()


def _cache_path(cache_dir: Path, key: str) -> Path:
    return Path(cache_dir) / f'lidar_chunk_{key[:32]}.npz'


def _read_cached(path: Path, key: str) -> Registration | None:
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data['key']) != key:
                return None
            return Registration.from_arrays(data)
    except Exception as err:  # noqa: B902 - any unreadable cache is recomputed, never fatal
        _LOG.warning('ignoring unreadable ground-truth cache %s (%s); recomputing', path, err)
        return None


def _write_cached(path: Path, key: str, registration: Registration) -> str:
    """Cache one chunk; return why it could not be (a cache is a help, never a failure)."""
    buffer = io.BytesIO()
    np.savez(buffer, key=np.array(key), **registration.to_arrays())
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, buffer.getvalue(), force=True)
    except (OSError, OutputError) as err:
        return str(err)
    return ''


# -- running the tasks --------------------------------------------------------------------------
class _Tally:
    """Frames read per chunk, reported as one total to the progress callback."""

    def __init__(self, total: int, on_progress: Progress | None) -> None:
        self.total = max(int(total), 1)
        self.done: dict[int, int] = {}
        self.on_progress = on_progress

    def update(self, index: int, frames: int) -> None:
        self.done[index] = max(self.done.get(index, 0), int(frames))
        if self.on_progress is not None:
            self.on_progress(min(sum(self.done.values()), self.total), self.total)

    def finish(self) -> None:
        if self.on_progress is not None:
            self.on_progress(self.total, self.total)


def _outcome(task: ChunkTask, arrays: Mapping[str, Any]) -> ChunkOutcome:
    return ChunkOutcome(task, Registration.from_arrays(arrays), None,
                        list(arrays.get('notes', [])))


def _failed(task: ChunkTask, err: BaseException) -> ChunkOutcome:
    return ChunkOutcome(task, None, f'{type(err).__name__}: {err}')


def _run_here(tasks: Sequence[ChunkTask], tally: _Tally,
              store: Callable[[ChunkOutcome], None]) -> None:
    for task in tasks:
        try:
            arrays = run_chunk(task, on_frame=lambda n, i=task.index: (
                tally.update(i, n) if n % _PROGRESS_EVERY == 0 else None))
            store(_outcome(task, arrays))
        except Exception as err:  # noqa: B902 - a failed chunk is named, the others kept
            store(_failed(task, err))


def _pool_context() -> Any:
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context('forkserver' if 'forkserver' in methods else 'spawn')


@contextlib.contextmanager
def _bare_main() -> Iterator[None]:
    """Start worker processes without re-running the parent's main module in each of them.

    A forkserver or spawn worker first imports the module the parent was started as (its
    ``__main__``: for ``skidkin`` the whole CLI with every command, scipy and matplotlib, about
    1.5 s of CPU per worker) before it unpickles a task. The tasks name their functions by
    module (this one), so the workers need none of it: while the pool starts its processes the
    parent's ``__main__`` is an empty module with no file and no spec, and multiprocessing then
    asks the workers to import nothing but what the task names.
    """
    real = sys.modules.get('__main__')
    sys.modules['__main__'] = types.ModuleType('__main__')
    try:
        yield
    finally:
        if real is None:
            del sys.modules['__main__']
        else:
            sys.modules['__main__'] = real


def _run_pool(tasks: Sequence[ChunkTask], jobs: int, tally: _Tally,
              store: Callable[[ChunkOutcome], None]) -> list[ChunkTask]:
    """Run tasks on a process pool; return the tasks left unfinished by a dead worker."""
    context = _pool_context()
    queue = context.SimpleQueue()
    executor = ProcessPoolExecutor(min(jobs, len(tasks)), mp_context=context,
                                   initializer=_init_worker, initargs=(queue,))
    # Not fork: the pool starts all its processes at the first submit, in this thread.
    with _bare_main():
        pending = {executor.submit(run_chunk, task): task for task in tasks}
    unfinished: list[ChunkTask] = []
    try:
        while pending:
            done, _ = wait(list(pending), timeout=0.5, return_when=FIRST_COMPLETED)
            while not queue.empty():
                tally.update(*queue.get())
            for future in done:
                task = pending.pop(future)
                try:
                    store(_outcome(task, future.result()))
                except BrokenProcessPool:
                    unfinished.append(task)
                except Exception as err:  # noqa: B902 - a failed chunk is named, not fatal
                    store(_failed(task, err))
    except KeyboardInterrupt:
        # Ctrl-C: the workers ignore it (left to this process); stop them now rather than wait
        # for their chunks (seconds each). What finished is cached already.
        for process in list((getattr(executor, '_processes', None) or {}).values()):
            process.terminate()
        raise
    finally:
        executor.shutdown(wait=True, cancel_futures=True)
    return unfinished


def _run_isolated(tasks: Sequence[ChunkTask], tally: _Tally,
                  store: Callable[[ChunkOutcome], None]) -> None:
    """Rerun tasks one per fresh process, so a task that kills its worker is the one named."""
    for task in tasks:
        left = _run_pool([task], 1, tally, store)
        if left:
            store(ChunkOutcome(task, None, 'the worker process died while registering this '
                                           'chunk (kiss-icp aborted, or out of memory)'))


def _run_dask(tasks: Sequence[ChunkTask], address: str, tally: _Tally,
              store: Callable[[ChunkOutcome], None]) -> None:
    # The address checked, a deadline on the connection, workers waited for (adapters.cluster).
    client = cluster.connect(address)
    try:
        cluster.wait_for_workers(client, address)
        futures = {client.submit(run_chunk, task, pure=False,
                                 key=f'skidkin-chunk-{task.index}-{os.getpid()}-{id(task)}'):
                   task for task in tasks}
        for future in cluster.finished(client, list(futures), address):
            task = futures[future]
            if future.status == 'error':
                store(_failed(task, future.exception()))
                continue
            outcome = _outcome(task, future.result())
            tally.update(task.index, len(outcome.registration))
            store(outcome)
    finally:
        client.close()


def run_chunks(tasks: Sequence[ChunkTask], options: ChunkOptions, *,
               cache_dir: Path | None = None, identity: Mapping[str, Any] | None = None,
               total_frames: int = 0, on_progress: Progress | None = None
               ) -> list[ChunkOutcome]:
    """Return every task's outcome, from the cache where it has it, else computed and cached."""
    outcomes: dict[int, ChunkOutcome] = {}
    keys: dict[int, str] = {}
    tally = _Tally(total_frames, on_progress)
    todo = []
    for task in tasks:
        if cache_dir is not None and identity is not None:
            keys[task.index] = chunk_key(task, identity)
            cached = _read_cached(_cache_path(cache_dir, keys[task.index]), keys[task.index])
            if cached is not None:
                outcomes[task.index] = ChunkOutcome(task, cached, cached=True)
                tally.update(task.index, len(cached))
                continue
        todo.append(task)

    unwritable: list[str] = []

    def store(outcome: ChunkOutcome) -> None:
        outcomes[outcome.task.index] = outcome
        if outcome.registration is not None:
            tally.update(outcome.task.index, len(outcome.registration))
            if outcome.task.index in keys and not unwritable:
                why = _write_cached(_cache_path(cache_dir, keys[outcome.task.index]),
                                    keys[outcome.task.index], outcome.registration)
                if why:  # said once; the other chunks are not tried (nor failed) either
                    unwritable.append(why)
                    _LOG.warning('the ground-truth cache %s cannot be written (%s): the ground '
                                 'truth is computed and written as usual, but not cached; '
                                 'give a writable --cache-dir to resume an interrupted run',
                                 cache_dir, why)
        else:
            _LOG.warning('chunk %d failed: %s', outcome.task.index, outcome.error)

    if todo and options.cluster:
        _run_dask(todo, options.cluster, tally, store)
    elif todo and options.jobs > 1 and len(todo) > 1:
        left = _run_pool(todo, options.jobs, tally, store)
        _run_isolated(left, tally, store)
    elif todo:
        _run_here(todo, tally, store)
    tally.finish()
    return [outcomes[task.index] for task in tasks]


# -- joining ------------------------------------------------------------------------------------
@dataclass
class Joined:
    """The joined registration, the frames that start behind a cut seam, and what happened.

    ``seams_tested``: seams whose overlap was compared; ``seams_failed``: those of them that
    disagreed (cut); ``seams_untested``: seams cut without a test (after a failed chunk, or no
    frame registered by both chunks). ``seams_cut`` is their sum (a cut seam with no frame after
    it is not counted: there is nothing to cut).
    """

    registration: Registration
    cut_frames: list[int]
    notes: list[str]
    seams_tested: int = 0
    seams_failed: int = 0
    seams_untested: int = 0

    @property
    def seams_cut(self) -> int:
        return self.seams_failed + self.seams_untested

    def seams_note(self, chunks: int, options: ChunkOptions) -> str:
        """Return the one-line summary of the chunks and their seams."""
        note = (f'lidar registered in {chunks} chunks of {options.chunk_s:g} s '
                f'({options.overlap_s:g} s overlap): {self.seams_tested} seam(s) tested, '
                f'{self.seams_failed} of them cut')
        if self.seams_untested:
            note += (f'; {self.seams_untested} cut untested (after a failed chunk or without a '
                     'frame both chunks registered)')
        return note


def _motion(pose_a: np.ndarray, pose_b: np.ndarray) -> np.ndarray:
    return np.linalg.inv(pose_a) @ pose_b


def _rotation_angle(transform: np.ndarray) -> float:
    return math.acos(max(-1.0, min(1.0, (float(np.trace(transform[:3, :3])) - 1.0) / 2.0)))


def _seam_agrees(previous: Registration, prev_rows: np.ndarray, current: Registration,
                 cur_rows: np.ndarray, window_ns: int, options: ChunkOptions) -> bool:
    """Tell whether both chunks moved alike over the common frames before the anchor."""
    anchor_end = previous.end_ns[prev_rows[-1]]
    use = previous.end_ns[prev_rows] >= anchor_end - window_ns
    a_prev, a_cur = previous.lidar_pose[prev_rows[-1]], current.lidar_pose[cur_rows[-1]]
    for i, j in zip(prev_rows[use], cur_rows[use]):
        m_prev = _motion(previous.lidar_pose[i], a_prev)
        m_cur = _motion(current.lidar_pose[j], a_cur)
        moved = float(np.linalg.norm(m_prev[:3, 3]))
        turned = _rotation_angle(m_prev)
        if (np.linalg.norm(m_prev[:3, 3] - m_cur[:3, 3]) > options.seam_abs_m + 0.1 * moved
                or _rotation_angle(_motion(m_prev, m_cur)) > options.seam_abs_rad
                + 0.1 * turned):
            return False
    return True


def join_chunks(outcomes: Sequence[ChunkOutcome], options: ChunkOptions) -> Joined:
    """Join chunk registrations into one (see the module docstring, steps 4 and 5)."""
    parts: list[Registration] = []
    cut: list[int] = []
    notes: list[str] = []
    tested = failed = untested = 0
    offset = 0
    previous: Registration | None = None  # the previous chunk, poses in the joined frame
    window_ns = s_to_ns(options.overlap_s / 2)
    for outcome in outcomes:
        task, reg = outcome.task, outcome.registration
        if reg is None:
            notes.append(f'lidar chunk {task.index} ({_window_text(task)}) failed: '
                         f'{outcome.error}; its frames have no ground truth, the other chunks '
                         'are kept')
            previous = None
            continue
        notes.extend(outcome.notes)
        receive = reg.receive_ns if reg.receive_ns is not None else reg.end_ns
        own = np.ones(len(reg), dtype=bool) if task.seam_ns is None else receive >= task.seam_ns
        first_own = np.flatnonzero(own & reg.registered)
        poses = reg.lidar_pose
        if parts:
            transform, agrees = (None, False) if previous is None else _anchor(
                previous, reg, window_ns, options)
            anchored = transform is not None
            if anchored:
                tested += 1
                if not agrees:
                    notes.append(f'lidar chunk {task.index}: its overlap with chunk '
                                 f'{task.index - 1} disagrees; the seam is cut')
            else:
                if previous is not None:
                    notes.append(f'lidar chunk {task.index}: no frame registered by both '
                                 'chunks at its seam; the seam is cut')
                transform = _continue_from(parts, reg, first_own)
            poses = np.einsum('ij,njk->nik', transform, poses)
            if not agrees and first_own.size:
                cut.append(offset + int(np.count_nonzero(own[:first_own[0]])))
                if anchored:
                    failed += 1
                else:
                    untested += 1
        previous = Registration(reg.end_ns, reg.status, reg.pose_t_ns, poses,
                                reg.inlier_fraction, reg.residual_m, reg.degeneracy, receive)
        part = _select(previous, own)
        parts.append(part)
        offset += len(part)
    if not parts:
        raise DataError('every lidar chunk failed; no ground truth: ' + '; '.join(notes))
    return Joined(_concatenate(parts), cut, notes, tested, failed, untested)


def _continue_from(parts: Sequence[Registration], reg: Registration,
                   first_own: np.ndarray) -> np.ndarray:
    """Return the transform that puts a chunk's first pose on the last joined pose (no anchor)."""
    for part in reversed(parts):
        rows = np.flatnonzero(part.registered)
        if rows.size and first_own.size:
            return part.lidar_pose[rows[-1]] @ np.linalg.inv(reg.lidar_pose[first_own[0]])
    return np.eye(4)


def _window_text(task: ChunkTask) -> str:
    start = 'start' if task.start_ns is None else f'{task.start_ns * 1e-9:.1f} s'
    stop = 'end' if task.stop_ns is None else f'{task.stop_ns * 1e-9:.1f} s'
    return f'bag time {start} to {stop}'


def _anchor(previous: Registration, current: Registration, window_ns: int,
            options: ChunkOptions) -> tuple[np.ndarray | None, bool]:
    """Return (transform onto the previous chunk's frame, seam test passed), None: no anchor."""
    common, prev_idx, cur_idx = np.intersect1d(previous.end_ns[previous.registered],
                                               current.end_ns[current.registered],
                                               return_indices=True)
    if common.size == 0:
        return None, False
    prev_rows = np.flatnonzero(previous.registered)[prev_idx]
    cur_rows = np.flatnonzero(current.registered)[cur_idx]
    transform = (previous.lidar_pose[prev_rows[-1]]
                 @ np.linalg.inv(current.lidar_pose[cur_rows[-1]]))
    return transform, _seam_agrees(previous, prev_rows, current, cur_rows, window_ns, options)


def _select(reg: Registration, keep: np.ndarray) -> Registration:
    return Registration(reg.end_ns[keep], tuple(s for s, k in zip(reg.status, keep) if k),
                        reg.pose_t_ns[keep], reg.lidar_pose[keep], reg.inlier_fraction[keep],
                        reg.residual_m[keep], reg.degeneracy[keep],
                        None if reg.receive_ns is None else reg.receive_ns[keep])


def _concatenate(parts: Sequence[Registration]) -> Registration:
    status: list[str] = []
    for part in parts:
        status.extend(part.status)
    return Registration(
        np.concatenate([p.end_ns for p in parts]), tuple(status),
        np.concatenate([p.pose_t_ns for p in parts]),
        np.concatenate([p.lidar_pose for p in parts]),
        *(np.concatenate([getattr(p, name) for p in parts])
          for name in ('inlier_fraction', 'residual_m', 'degeneracy')),
        receive_ns=np.concatenate([p.receive_ns if p.receive_ns is not None else p.end_ns
                                   for p in parts]))


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
    plan = _Plan(str(path), topic, first_receive, period_ns, n_frames, int(first[0].end_ns),
                 options)
    tasks = plan.tasks(config)
    samples: list[tuple[tuple[int, int | None], ChunkTask]] = []
    reference = reference_config(config)
    notes: list[str] = []
    if check.enabled and automatic and finer_than_reference(config, reference):
        notes.append(f'kiss-icp settings: the voxel from the data ({config.voxel_size_m:g} m) is '
                     f"finer than kiss-icp's ({reference.voxel_size_m:g} m), where the fast "
                     "settings are not faster: kiss-icp's defaults are used")
        config = reference
        tasks = plan.tasks(config)
    span_ns = max(n_frames - 1, 0) * period_ns
    if (check.enabled and automatic and reference != config
            and span_ns >= (check.window_s + check.warmup_s) * NS_PER_S):
        windows = plan_samples([t.stop_ns for t in tasks], first_receive, first_receive + span_ns,
                               check)
        samples = [(window, ChunkTask(str(path), topic, _SAMPLE_INDEX + k, window[0],
                                      window[1], None, reference, tasks[0].grid))
                   for k, window in enumerate(windows)]
    identity = bag_identity(path) if cache_dir is not None else None
    cache = None if cache_dir is None else Path(cache_dir)
    sample_frames = sum(int((check.window_s + check.warmup_s) * NS_PER_S / period_ns)
                        for _ in samples)
    outcomes = run_chunks(tasks + [task for _, task in samples], options, cache_dir=cache,
                          identity=identity, total_frames=plan.frames(len(tasks)) + sample_frames,
                          on_progress=on_progress)
    outcomes, sampled = outcomes[:len(tasks)], outcomes[len(tasks):]
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
    elif check.enabled and not notes:
        notes.append('kiss-icp settings not self-checked: ' + (
            'they were set explicitly' if not automatic or reference == config
            else 'the recording is shorter than one sample window'))
    joined = join_chunks(outcomes, options)
    notes = list(dict.fromkeys(joined.notes)) + notes
    if len(tasks) > 1:
        notes.append(joined.seams_note(len(tasks), options))
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

    def tasks(self, config: IcpConfig) -> list[ChunkTask]:
        return plan_chunks(self.bag, self.topic, self.first_receive_ns, self.period_ns,
                           self.n_frames, self.first_end_ns, config, self.options)

    def frames(self, n_tasks: int) -> int:
        """Return the frames all chunks read: the recording and every warm-up."""
        warmup = int(self.options.overlap_s * NS_PER_S / self.period_ns)
        return self.n_frames + warmup * (n_tasks - 1)
