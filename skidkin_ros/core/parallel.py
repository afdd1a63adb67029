"""Run independent tasks on several cores by forking: the workers see this process's memory.

The diagnosis fits dozens of independent candidate/fold combinations over the same (large)
segment arrays. Forked workers inherit those arrays instead of receiving a pickled copy per
task; only the task arguments and the results cross process boundaries. Where ``fork`` is not
available (Windows), inside a worker, or with ``jobs <= 1``, the tasks run here, one after the
other. The results are the same either way: each task runs the same code on the same inputs.

:func:`one_blas_thread` keeps numpy's BLAS on one thread. Every matrix here is tiny (3 x 3
covariances, a few dozen parameters), and a multi-threaded BLAS only adds synchronisation: on a
busy 2-core machine, scipy's L-BFGS-B spent 20 ms per iteration waiting for OpenBLAS threads, and
one noise fit took 10.9 s instead of 1.1 s (a one-off profile); ``make bench`` (part
``calibration``) times a calibration both ways: 5.6x faster with one thread under load, the same
on a quiet machine. Forked workers with threaded BLAS would oversubscribe the cores as well.
"""

from __future__ import annotations

from concurrent.futures import as_completed, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
import multiprocessing
import os
import signal
from typing import Any, Callable, Iterator, Sequence

from skidkin_ros.errors import SkidkinError
from threadpoolctl import threadpool_limits

__all__ = ['fork_map', 'usable_cpus', 'one_blas_thread']

# What the forked workers run: set just before the pool forks, cleared after it closes.
_TASK: Callable[[Any], Any] | None = None
_ITEMS: Sequence[Any] = ()


def usable_cpus() -> int:
    """Return the number of CPUs this process may run on."""
    if hasattr(os, 'sched_getaffinity'):
        return max(len(os.sched_getaffinity(0)), 1)
    return max(os.cpu_count() or 1, 1)


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """Run the block with numpy's BLAS on one thread (module docstring); restore it after."""
    with threadpool_limits(limits=1, user_api='blas'):
        yield


def _run(index: int) -> tuple[int, Any]:
    assert _TASK is not None
    return index, _TASK(_ITEMS[index])


def _worker_signals() -> None:
    """Give a worker the default SIGTERM and no SIGINT, whatever the parent installed.

    A parent that runs rclpy has its own SIGTERM/SIGINT handlers, and a forked worker inherits
    them: it would then survive being terminated, and waiting for it would never end. Ctrl-C is
    the parent's to handle.
    """
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _can_fork() -> bool:
    return ('fork' in multiprocessing.get_all_start_methods()
            and not multiprocessing.current_process().daemon)


def fork_map(task: Callable[[Any], Any], items: Sequence[Any], jobs: int,
             on_done: Callable[[int, int], None] | None = None) -> list[Any]:
    """Return ``[task(item) for item in items]``, computed by up to ``jobs`` forked workers.

    ``task`` may be any callable (a bound method, a closure): the workers inherit it by fork.
    Its results must pickle. ``on_done(done, total)`` is called here as each task finishes.
    An exception in a task is raised here, once the tasks already running have finished (those
    not started are cancelled); a worker that dies (killed, out of memory) raises SkidkinError.
    """
    global _TASK, _ITEMS
    items = list(items)
    total = len(items)
    jobs = min(int(jobs), total)
    if jobs <= 1 or not _can_fork() or _TASK is not None:
        results = []
        for done, item in enumerate(items, 1):
            results.append(task(item))
            if on_done is not None:
                on_done(done, total)
        return results
    results = [None] * total
    _TASK, _ITEMS = task, items
    executor = ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context('fork'),
                                   initializer=_worker_signals)
    try:
        futures = {executor.submit(_run, index) for index in range(total)}
        for done, future in enumerate(as_completed(futures), 1):
            index, value = future.result()
            results[index] = value
            if on_done is not None:
                on_done(done, total)
    except BrokenProcessPool as err:
        raise SkidkinError(
            'a worker process died before finishing its task (killed, or out of memory?); '
            'rerun with fewer processes (--jobs 1 runs everything in this process)') from err
    finally:
        executor.shutdown(wait=True, cancel_futures=True)
        _TASK, _ITEMS = None, ()
    return results
