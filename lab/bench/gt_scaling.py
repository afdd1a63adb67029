"""What bounds the chunked ground truth's scaling: per-task CPU, the serial part, a schedule.

On a machine shared with others, wall time with N processes says more about the others than
about the code. This study measures what does not depend on them, the CPU time of every part,
and predicts the wall time on N free cores from it:

1. **Serial part** (in the parent, before and after the workers): importing the CLI (a
   subprocess, its CPU time), opening the bag and planning, reading the wheels and IMU,
   comparing the self-check's samples, joining and guarding, all in this process with the
   CPU clock around each step (:func:`serial_steps`).
2. **Tasks**: ``skidkin_ros.adapters.lidar_chunks.bag_ground_truth`` is run with one process;
   every task it runs (the chunks, the self-check's sample windows, a second round when the
   check rejects the fast settings) is timed on the CPU clock (:func:`task_times`).
3. **Schedule**: the tasks in the order the pool submits them, each to the first free process
   (what ``ProcessPoolExecutor`` does), on N processes; predicted wall = serial + worker start
   + the schedule's length; efficiency = predicted wall for 1 / (N x predicted wall for N).

The prediction assumes N free cores that run a task as fast as one (no memory-bandwidth or
turbo effects): an upper bound of what N processes give. ``python lab/bench/gt_scenes.py
--jobs-list 1 2 4 8 16`` measures the real thing where such a machine exists.

    python lab/bench/gt_scaling.py --scene forest --duration 200 --chunk-s 20
"""

from __future__ import annotations

import argparse
import heapq
import json
from pathlib import Path
import subprocess
import sys
import tempfile
import time
from typing import Any, Sequence

import gt_scenes

# CPU s for a worker to start (fork from the preloaded forkserver: nothing left to import).
_WORKER_START_S = 0.05


def cli_import_cpu_s() -> float:
    """Return the CPU time (s) of ``import skidkin_ros.cli.main`` in a fresh interpreter."""
    code = ('import time; c = time.process_time(); import skidkin_ros.cli.main; '
            'print(time.process_time() - c)')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True)
    return float(out.stdout.strip())


def task_times(bag: Path, chunk_s: float) -> tuple[list[tuple[str, float]], dict[str, float]]:
    """Run the ground truth of ``bag`` in this process; return each task's CPU s, the steps'.

    Tasks come back in the order the pool would submit them (one list per ``run_chunks``
    call, joined); steps: CPU s of the parent's serial steps.
    """
    from skidkin_ros.adapters import lidar_chunks, lidar_pool, sources

    tasks: list[tuple[str, float]] = []
    steps: dict[str, float] = {}
    real_run_chunk = lidar_pool.run_chunk

    def timed_chunk(task: Any, on_frame: Any = None) -> Any:
        tic = time.process_time()
        try:
            return real_run_chunk(task, on_frame=on_frame)
        finally:
            kind = 'sample' if task.index >= 100_000 else 'chunk'
            tasks.append((f'{kind} {task.index % 100_000}', time.process_time() - tic))

    def timed_step(module: Any, name: str, label: str) -> None:
        real = getattr(module, name)

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            tic = time.process_time()
            try:
                return real(*args, **kwargs)
            finally:
                steps[label] = steps.get(label, 0.0) + time.process_time() - tic
        setattr(module, name, wrapper)

    lidar_pool.run_chunk = timed_chunk
    timed_step(sources, 'open_recording', 'open the bag')
    timed_step(sources, '_read_wheels', 'read the wheels')
    timed_step(lidar_chunks, 'check_samples', 'compare the self-check samples')
    timed_step(lidar_chunks, 'join_chunks', 'join the chunks')
    timed_step(lidar_chunks, 'guarded_truth', 'guard')
    timed_step(sources, '_icp_truth', 'ground truth (all)')
    from skidkin_ros.cli.main import main

    with tempfile.TemporaryDirectory() as tmp:
        tic = time.process_time()
        main(['--quiet', 'groundtruth', str(bag), '--out', str(Path(tmp) / 'gt.csv'),
              '--no-cache', '--no-progress', '--jobs', '1', '--chunk-s', f'{chunk_s:g}'])
        steps['command (all)'] = time.process_time() - tic
    lidar_pool.run_chunk = real_run_chunk
    return tasks, steps


def schedule_s(costs: Sequence[float], processes: int) -> float:
    """Return the length (s) of running ``costs`` in order, each on the first free process."""
    free = [0.0] * max(1, min(processes, len(costs)))
    for cost in costs:
        start = heapq.heappop(free)
        heapq.heappush(free, start + cost)
    return max(free) if costs else 0.0


def predict(serial_s: float, costs: Sequence[float], rounds: Sequence[int],
            jobs_list: Sequence[int]) -> list[dict[str, float]]:
    """Return the predicted wall time and efficiency for each number of processes.

    ``rounds``: how many tasks each ``run_chunks`` call ran (a rejected self-check makes a
    second call that starts when the first has finished).
    """
    rows = []
    for n in jobs_list:
        wall, start = serial_s, 0
        for count in rounds:
            part = list(costs[start:start + count])
            start += count
            wall += schedule_s(part, n) + (_WORKER_START_S if n > 1 else 0.0)
        rows.append({'processes': n, 'wall_s': wall})
    one = rows[0]['wall_s'] if rows and rows[0]['processes'] == 1 else None
    for row in rows:
        if one is not None:
            row['speedup'] = one / row['wall_s']
            row['efficiency'] = row['speedup'] / row['processes']
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--scene', default='forest', choices=gt_scenes.SCENES)
    parser.add_argument('--duration', type=float, default=200.0, help='s of recording')
    parser.add_argument('--chunk-s', type=float, default=20.0, help='chunk length (s)')
    parser.add_argument('--seed', type=int, default=5)
    parser.add_argument('--jobs-list', type=int, nargs='+', default=[1, 2, 4, 8, 10, 16])
    parser.add_argument('--json', type=Path, help='also write the results here')
    args = parser.parse_args(argv)
    from skidkin_ros.adapters.sim_writer import write_bag
    from skidkin_ros.sim import simulate

    print(f'  load average {gt_scenes.load_average()}', flush=True)
    with tempfile.TemporaryDirectory(prefix='gt_scaling_') as tmp:
        sim = simulate(gt_scenes.scene_config(args.scene, args.duration, args.seed))
        bag, _ = write_bag(sim, Path(tmp) / 'bag')
        tasks, steps = task_times(bag, args.chunk_s)
    importing = cli_import_cpu_s()
    task_cpu = sum(cost for _, cost in tasks)
    serial = importing + steps['command (all)'] - task_cpu
    # a second round of chunks (the check rejected the fast settings) restarts the numbering
    rounds, count = [], 0
    for k, (name, _) in enumerate(tasks):
        if k and name == 'chunk 0':
            rounds.append(count)
            count = 0
        count += 1
    rounds.append(count)
    rows = predict(serial, [cost for _, cost in tasks], rounds, args.jobs_list)
    print(f'\n{args.scene}, {args.duration:g} s, chunks of {args.chunk_s:g} s, '
          f'load average {gt_scenes.load_average()}')
    print('\n| serial step (parent) | CPU s |\n|---|---|')
    print(f'| import the CLI | {importing:.2f} |')
    for label, value in steps.items():
        print(f'| {label} | {value:.2f} |')
    print(f'| serial in all (import + command - tasks) | {serial:.2f} |')
    print('\n| task | CPU s |\n|---|---|')
    for name, cost in tasks:
        print(f'| {name} | {cost:.2f} |')
    print('\n| processes | predicted wall s | speed-up | efficiency |\n|---|---|---|---|')
    for row in rows:
        print(f'| {row["processes"]} | {row["wall_s"]:.1f} | {row.get("speedup", 0):.2f} | '
              f'{100 * row.get("efficiency", 0):.0f} % |')
    if args.json:
        args.json.write_text(json.dumps({'tasks': tasks, 'steps': steps, 'serial_s': serial,
                                         'rounds': rounds, 'predicted': rows}, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
