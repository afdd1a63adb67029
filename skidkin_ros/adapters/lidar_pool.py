"""Running chunk tasks: here, on a local process pool, or on a Dask cluster, with progress.

One job: step 2 of :mod:`skidkin_ros.adapters.lidar_chunks` (and 5's naming of failed chunks).
Workers leave Ctrl-C to the parent, which stops them at once; a worker that dies takes only its
own chunk; every finished chunk is cached as it arrives (:mod:`skidkin_ros.adapters.lidar_cache`).
"""

from __future__ import annotations

from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
import contextlib
import logging
import multiprocessing
import os
from pathlib import Path
import signal
import sys
import types
from typing import Any, Callable, Iterator, Mapping, Sequence

from skidkin_ros.adapters import cluster
from skidkin_ros.adapters.lidar_cache import _cache_path, _read_cached, _write_cached, chunk_key
from skidkin_ros.adapters.lidar_gt import register_frames, Registration
from skidkin_ros.adapters.lidar_plan import ChunkOptions, ChunkOutcome, ChunkTask

__all__ = ['Progress', 'run_chunk', 'run_chunks']

# The chunked ground truth logs under one name, that of lidar_chunks, wherever the code lives.
_LOG = logging.getLogger('skidkin_ros.adapters.lidar_chunks')
Progress = Callable[[int, int], None]
# Frames between two progress messages of a worker.
_PROGRESS_EVERY = 10


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


# What a chunk imports (about 0.5 s of CPU): the forkserver imports it once, and every worker
# forked from it starts with it, instead of each worker importing it again.
_WORKER_MODULES = ('skidkin_ros.adapters.lidar_pool', 'skidkin_ros.adapters.bag_reader',
                   'kiss_icp.kiss_icp', 'scipy.spatial')


def _pool_context() -> Any:
    methods = multiprocessing.get_all_start_methods()
    if 'forkserver' not in methods:
        return multiprocessing.get_context('spawn')
    context = multiprocessing.get_context('forkserver')
    # Only read when the forkserver starts (the first pool of this process); a module that
    # fails to import there is imported by the worker that needs it, as without the preload.
    context.set_forkserver_preload(list(_WORKER_MODULES))
    return context


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
