"""fork_map: the diagnosis's candidate fits on several cores, with the serial result."""

import os
import subprocess
import sys

import numpy as np
import pytest
from skidkin_ros.cli.common import RoundBars
from skidkin_ros.core.parallel import fork_map, usable_cpus
from skidkin_ros.errors import SkidkinError


def test_forked_results_equal_the_serial_ones_in_order():
    data = np.random.default_rng(0).normal(size=(200, 50))  # inherited, not pickled per task

    def task(row):  # a closure: only a fork can hand it to a worker
        return float(np.linalg.norm(data[row] @ data.T)), os.getpid()

    rows = list(range(40))
    serial = fork_map(task, rows, jobs=1)
    forked = fork_map(task, rows, jobs=2)
    assert [value for value, _ in forked] == [value for value, _ in serial]
    assert {pid for _, pid in serial} == {os.getpid()}
    assert os.getpid() not in {pid for _, pid in forked}  # the workers did the work


def test_progress_counts_every_task_and_errors_reach_the_caller():
    seen = []
    assert fork_map(lambda x: x * x, [3, 1, 2], jobs=2,
                    on_done=lambda done, total: seen.append((done, total))) == [9, 1, 4]
    assert seen == [(1, 3), (2, 3), (3, 3)]

    def fails(x):
        if x == 2:
            raise ValueError(f'bad item {x}')
        return x

    with pytest.raises(ValueError, match='bad item 2'):
        fork_map(fails, [1, 2, 3], jobs=2)
    assert fork_map(fails, [1, 3], jobs=2) == [1, 3]  # and the next map still works


def test_a_worker_that_dies_is_a_clear_error_not_a_hang():
    def dies(x):
        if x == 3:
            os._exit(9)  # what the out-of-memory killer leaves behind
        return x

    with pytest.raises(SkidkinError, match='worker process died.*--jobs 1'):
        fork_map(dies, list(range(6)), jobs=2)
    assert fork_map(dies, [1, 2], jobs=2) == [1, 2]


def test_a_task_that_maps_again_runs_its_inner_map_in_place():
    def outer(x):
        return os.getpid(), fork_map(lambda y: (y, os.getpid()), [x, x + 1], jobs=2)

    for worker, inner in fork_map(outer, [0, 10], jobs=2):
        assert worker != os.getpid()
        assert {pid for _, pid in inner} == {worker}  # no pool inside a worker: run in place
    assert usable_cpus() >= 1


def test_round_bars_restart_per_round_and_reach_their_totals(capsys):
    bars = RoundBars()
    for done in range(1, 4):
        bars(1, done, 3)
    bars(1, 1, 4)  # the sparse fallback's fits: a new batch in the same round
    bars(2, 2, 2)
    bars.close()
    # stderr is not a terminal here: a line per 10 % of each batch (cli.progress)
    lines = capsys.readouterr().err.splitlines()
    assert lines[0].startswith('diagnose, round 1: 33 % (1/3 fits)')
    assert lines[2].startswith('diagnose, round 1: 100 % (3/3 fits)')
    assert lines[3].startswith('diagnose, round 1: 25 % (1/4 fits)')
    assert lines[-1].startswith('diagnose, round 2: 100 % (2/2 fits)')


HANG_SCRIPT = """
import rclpy
from skidkin_ros.core.parallel import fork_map
rclpy.init()  # installs rclpy's SIGINT/SIGTERM handlers, which forked workers inherit


def fails(x):
    if x == 2:
        raise ValueError('bad')
    return x


for _ in range(3):
    try:
        fork_map(fails, [1, 2, 3, 4, 5], jobs=2)  # the pool is terminated on the error
    except ValueError:
        pass
    assert fork_map(lambda x: x + 1, list(range(6)), jobs=2) == [1, 2, 3, 4, 5, 6]
rclpy.shutdown()
print('ok')
"""


@pytest.mark.ros
def test_workers_stop_in_a_process_that_runs_rclpy():
    """A worker inherits rclpy's signal handlers; it once lived through terminate() (a hang)."""
    proc = subprocess.run([sys.executable, '-c', HANG_SCRIPT], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip() == 'ok', proc.stderr[-2000:]
