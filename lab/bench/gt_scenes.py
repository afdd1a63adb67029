"""Ground truth on several scenes, scored against the simulator and timed against kiss-icp.

Scenes (skidkin_ros.sim.scene): the ``forest`` (400 trees), the ``courtyard`` (walls, boxes,
pillars; 0.5 deg lidar), a sparse ``snowfield`` (flat ground, a tree per 50 m2 over a larger
field) and an open ``plain`` (flat ground, six far posts: hard for ICP). Outdoor scenes use a
VLP-16-like lidar: 16 rings, 360 columns, 10 Hz, per-point times.

Per scene, on the same bag, as subprocesses, one after the other so all see the machine in the
same state (the machine is shared: only ratios measured in one run are reported):

* ``kiss``: plain ``kiss_icp_pipeline --topic /points BAG`` (kiss-icp's own pipeline, its
  defaults, its own threads on every core);
* ``before``: ``skidkin groundtruth --no-icp-check`` (the fast settings on every scene: the
  behaviour before the self-check), ``--jobs`` the first of ``--jobs-list``;
* ``after_jN``: ``skidkin groundtruth`` with the defaults and ``--jobs N`` for every N of
  ``--jobs-list`` (default 2 1; ``1 2 4 8 16`` on a machine with the cores).

Every skidkin run uses chunks of ``--chunk-s`` (default 20 s: the recordings are sized down
from a few minutes to about one, so the chunks are too, to keep several seams per scene).
``--repeat R`` runs every contender R times in turn and keeps the median wall and CPU time.

Scores against the simulator's truth: poses kept by the guard, seams tested and cut (from the
notes), the path length at 1 s steps (the per-frame path adds each frame's jitter) against the
true path at the same stamps, the median error of the 1 s increments of the kept poses (all
poses for kiss), and whether kiss-icp's own track is consistent (path within 10 % and 95 % of
its 1 s increments within 50 cm: no gross failure). Speed: kiss wall time / skidkin wall time,
and the same for the CPU time (user + system of the command and its processes: the pool's
workers are children of multiprocessing's forkserver, which outlives its parent; this process
becomes their reaper, Linux's PR_SET_CHILD_SUBREAPER, so their CPU time is counted too); on a
machine others load, CPU time is the steadier measure of work. Scaling: wall of ``--jobs 1``
over ``--jobs N`` and the parallel efficiency (that over N), and whether every N gave the CSV
of the first of ``--jobs-list`` byte for byte (``identical_jN`` in the JSON).

    python lab/bench/gt_scenes.py    # 4 scenes of 60 s, ~5 min on a quiet 2-core machine
    python lab/bench/gt_scenes.py --duration 120 --scenes forest snowfield
    # on a 16-core machine: 16 chunks per scene, 1 to 16 processes, median of 3 runs
    python lab/bench/gt_scenes.py --jobs-list 1 2 4 8 16 --repeat 3 --no-before --duration 320
"""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path
import re
import resource
import subprocess
import sys
import tempfile
import time
from typing import Any, Sequence

import gt_bench
import numpy as np

SCENES = ('forest', 'courtyard', 'snowfield', 'plain')


def scene_config(scene: str, duration_s: float, seed: int) -> Any:
    """Return the SimConfig of one benchmark scene."""
    from skidkin_ros.sim import LidarConfig, SimConfig

    if scene == 'courtyard':
        lidar = LidarConfig(azimuth_resolution_deg=0.5, mount_xyz_m=(0.3, 0.1, 0.5))
        return SimConfig(duration_s=duration_s, seed=seed, lidar=lidar, scene='courtyard',
                         internal_rate_hz=200.0)
    lidar = LidarConfig(n_rings=16, azimuth_resolution_deg=1.0, rate_hz=10.0,
                        range_noise_m=0.02, max_range_m=100.0, mount_xyz_m=(0.2, 0.0, 0.7))
    half = 16.0 if scene == 'forest' else 30.0
    return SimConfig(duration_s=duration_s, seed=seed, lidar=lidar, scene=scene,
                     scene_half_size_m=half, arena_radius_m=0.45 * half,
                     internal_rate_hz=200.0)


def _tool(name: str) -> str:
    return str(Path(sys.executable).with_name(name))


_CPU_S: dict[str, float] = {}
_PR_SET_CHILD_SUBREAPER = 36


def _adopt_orphans() -> bool:
    """Make this process the reaper of its descendants' orphans (Linux); return whether it is.

    A ``--jobs N`` run's workers are children of multiprocessing's forkserver, which its parent
    leaves behind at exit: without this their CPU time never reaches this process's
    RUSAGE_CHILDREN. With it the forkserver is re-parented here and reaped by :func:`_reap`.
    """
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(_PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _reap(timeout_s: float = 10.0) -> None:
    """Wait for every adopted orphan (the forkserver exits once its parent has gone)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            pid, _ = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            time.sleep(0.05)


def _timed(command: Sequence[str], env: dict[str, str] | None = None,
           cwd: Path | None = None) -> tuple[float, int, str]:
    """Run a command; return (wall s, exit code, stderr); its CPU s go to _CPU_S['last'].

    The CPU time counts the command's worker processes where :func:`_adopt_orphans` worked
    (``_CPU_S['workers_counted']``).
    """
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    tic = time.perf_counter()
    proc = subprocess.run(list(command), env=env, cwd=cwd, stdout=subprocess.DEVNULL,
                          stderr=subprocess.PIPE, text=True, timeout=3600)
    wall = time.perf_counter() - tic
    _reap()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    _CPU_S['last'] = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, proc.returncode, proc.stderr or ''


def _median_timed(command: Sequence[str], repeat: int, **kwargs: Any
                  ) -> tuple[float, float, int, str]:
    """Run a command ``repeat`` times; return (median wall s, median CPU s, code, stderr)."""
    walls, cpus = [], []
    code, err = 0, ''
    for _ in range(max(repeat, 1)):
        wall, code, err = _timed(command, **kwargs)
        if code != 0:
            break
        walls.append(wall)
        cpus.append(_CPU_S['last'])
    if not walls:
        return math.nan, math.nan, code, err
    return float(np.median(walls)), float(np.median(cpus)), code, err


def _old_env(old: Path) -> dict[str, str]:
    """Return the environment that makes ``skidkin`` import the skidkin_ros under ``old``."""
    return dict(os.environ, PYTHONPATH=str(old))


def load_average() -> str:
    """Return the 1, 5 and 15 min load averages (others' work on a shared machine)."""
    return ' '.join(f'{x:.2f}' for x in os.getloadavg())


def _read_csv(path: Path) -> Any:
    from skidkin_ros.core.drive import PoseTrack

    rows = np.genfromtxt(path, delimiter=',', names=True)
    return PoseTrack(rows['t_ns'].astype(np.int64), rows['x'], rows['y'], rows['yaw'],
                     rows['valid'].astype(bool))


def path_1s(t_ns: np.ndarray, x: np.ndarray, y: np.ndarray) -> float:
    """Return the path length (m) over the poses nearest to a 1 s grid."""
    grid = np.arange(t_ns[0], t_ns[-1] + 1, 1_000_000_000)
    rows = np.unique(np.clip(np.searchsorted(t_ns, grid), 0, t_ns.size - 1))
    return float(np.hypot(np.diff(x[rows]), np.diff(y[rows])).sum())


def score(track: Any, sim: Any, valid_only: bool) -> dict[str, Any]:
    """Score a base_link track against the simulator's truth."""
    from skidkin_ros.sim.accuracy import increment_errors

    true = np.asarray(sim.pose_at(track.t_ns))
    one = increment_errors(track, sim.pose_at, horizon_s=1.0, valid_only=valid_only)
    every = increment_errors(track, sim.pose_at, horizon_s=1.0, valid_only=False)
    true_path = path_1s(track.t_ns, true[:, 0], true[:, 1])
    path = path_1s(track.t_ns, track.x, track.y)
    p95 = float(np.percentile(every.position_m, 95)) if every.position_m.size else np.nan
    return {'poses': int(len(track)), 'kept': float(np.mean(track.valid)),
            'path_1s_m': path, 'true_path_1s_m': true_path,
            'path_ratio': path / true_path if true_path > 0 else np.nan,
            'path_frames_m': float(track.path_length()[-1]),
            'pos_1s_cm': 100 * one.median_position_m, 'yaw_1s_mrad': 1e3 * one.median_yaw_rad,
            'p95_1s_cm': 100 * p95}


def _notes(stderr: str) -> dict[str, Any]:
    tested = re.search(r'(\d+) seam\(s\) tested, (\d+) of them cut', stderr)
    untested = re.search(r'; (\d+) cut untested', stderr)
    check = ('defaults' if 'disagree with kiss-icp' in stderr else 'kept'
             if 'agree with kiss-icp' in stderr else 'defaults (fine voxel)'
             if "finer than kiss-icp's" in stderr else 'off')
    return {'seams_tested': int(tested.group(1)) if tested else 0,
            'seams_cut': (int(tested.group(2)) if tested else 0)
            + (int(untested.group(1)) if untested else 0), 'self_check': check,
            'check_note': next((line.strip() for line in stderr.splitlines()
                                if 'self-check' in line), ''),
            'seams_note': ' '.join(line.strip() for line in stderr.splitlines()
                                   if 'chunk seams' in line or 'tried again' in line)}


def run_scene(scene: str, duration_s: float, seed: int, work: Path, chunk_s: float = 20.0,
              jobs_list: Sequence[int] = (2, 1), repeat: int = 1,
              before: bool = True,
              variants: Sequence[tuple[str, Sequence[str]]] = (),
              old: Path | None = None, kiss_run: bool = True) -> dict[str, Any]:
    """Simulate one scene, run every contender on its bag, score and time them.

    Contenders: ``kiss``, ``before`` (unless ``before`` is False) and ``after_jN`` for every N
    of ``jobs_list``; each is run ``repeat`` times in turn and its median wall and CPU time
    kept; with ``old`` (a folder holding another version of skidkin_ros) also ``old_jN``, that
    code run beside this one. ``identical_jN``: the CSV of ``--jobs N`` equals that of the
    first of ``jobs_list`` byte for byte (``identical_old_jN``: that of ``old_jN``);
    ``scaling``: wall of ``--jobs 1`` over ``--jobs N`` (when 1 is listed) and the parallel
    efficiency, that speed-up over N.
    """
    from skidkin_ros.adapters.sim_writer import write_bag
    from skidkin_ros.sim import simulate

    sim = simulate(scene_config(scene, duration_s, seed))
    bag, _ = write_bag(sim, work / f'{scene}_{int(duration_s)}s')
    result: dict[str, Any] = {'scene': scene, 'duration_s': duration_s, 'seed': seed,
                              'load_before': load_average()}
    if kiss_run:
        env = dict(os.environ, kiss_icp_out_dir=str(work / f'kiss_{scene}'))
        seconds, cpu_s, code, err = _median_timed(
            [_tool('kiss_icp_pipeline'), '--topic', '/points', str(bag)], repeat, env=env,
            cwd=work)
        if code != 0:
            return {**result, 'error': f'kiss_icp_pipeline exited {code}: {err[-800:]}'}
        kiss = score(gt_bench.kiss_track(work / f'kiss_{scene}', bag), sim, valid_only=False)
        kiss.update(seconds=seconds, cpu_s=cpu_s)
        kiss['consistent'] = bool(abs(kiss['path_ratio'] - 1) <= 0.1
                                  and kiss['p95_1s_cm'] <= 50)
        result['kiss'] = kiss
    else:  # --no-kiss: ours (and --old) only; no ratio to kiss-icp
        kiss = {'seconds': math.nan, 'cpu_s': math.nan}
    chunks = ['--chunk-s', f'{chunk_s:g}']
    runs = [('before', ['--no-icp-check', '--jobs', str(jobs_list[0]), *chunks])] if before else []
    runs += [(f'after_j{n}', ['--jobs', str(n), *chunks]) for n in jobs_list]
    runs += [(f'after_j{jobs_list[0]}_{label}', ['--jobs', str(jobs_list[0]), *chunks, *extra])
             for label, extra in variants]
    if old is not None:
        runs += [(f'old_j{n}', ['--jobs', str(n), *chunks]) for n in jobs_list]
    for name, extra in runs:
        out = work / f'{scene}_{name}.csv'
        seconds, cpu_s, code, err = _median_timed(
            [_tool('skidkin'), 'groundtruth', str(bag), '--out', str(out), '--force',
             '--no-cache', '--no-progress', *extra], repeat,
            env=_old_env(old) if name.startswith('old_') else None)
        if code != 0:
            result[name] = {'error': f'exited {code}: {err[-800:]}'}
            continue
        row = score(_read_csv(out), sim, valid_only=True)
        row.update(_notes(err), seconds=seconds, speed_vs_kiss=kiss['seconds'] / seconds,
                   cpu_s=cpu_s, cpu_vs_kiss=kiss['cpu_s'] / cpu_s)
        result[name] = row
    first = work / f'{scene}_after_j{jobs_list[0]}.csv'
    for n in jobs_list[1:]:
        other = work / f'{scene}_after_j{n}.csv'
        if first.is_file() and other.is_file():
            result[f'identical_j{n}'] = first.read_bytes() == other.read_bytes()
    for n in jobs_list:
        mine, theirs = work / f'{scene}_after_j{n}.csv', work / f'{scene}_old_j{n}.csv'
        if mine.is_file() and theirs.is_file():
            result[f'identical_old_j{n}'] = mine.read_bytes() == theirs.read_bytes()
    one = result.get('after_j1')
    if one and 'seconds' in one:
        for n in jobs_list:
            row = result.get(f'after_j{n}')
            if row and 'seconds' in row:
                row['speedup_vs_j1'] = one['seconds'] / row['seconds']
                row['efficiency'] = row['speedup_vs_j1'] / n
    result['load_after'] = load_average()
    return result


def _number(value: float | None, digits: int) -> str:
    return '–' if value is None or not math.isfinite(value) else f'{value:.{digits}f}'


def table(results: Sequence[dict[str, Any]]) -> str:
    """Return the results as a Markdown table."""
    lines = ['| scene | run | wall s | × kiss | CPU s | × kiss CPU | j1 / jN wall (eff.) | kept '
             '| seams cut/tested | path 1 s / true | 1 s cm / mrad | check |',
             '|---|---|---|---|---|---|---|---|---|---|---|---|']
    for res in results:
        names = (['kiss'] if 'kiss' in res else []) + [
            k for k in res if k == 'before' or k.startswith(('after_j', 'old_j'))]
        for name in names:
            row = res.get(name)
            if not row or 'error' in row:
                lines.append(f'| {res["scene"]} | {name} | error | | | | | | | | | |')
                continue
            seams = ('' if name == 'kiss' else f'{row["seams_cut"]}/{row["seams_tested"]}')
            label = name + (' (consistent)' if row.get('consistent') else
                            ' (NOT consistent)' if name == 'kiss' else '')
            scaling = ('' if 'speedup_vs_j1' not in row else
                       f'{row["speedup_vs_j1"]:.2f} ({100 * row["efficiency"]:.0f} %)')
            lines.append(
                f'| {res["scene"]} | {label} | {row["seconds"]:.1f} | '
                f'{row.get("speed_vs_kiss", 1.0):.2f} | {_number(row.get("cpu_s"), 1)} | '
                f'{_number(row.get("cpu_vs_kiss", 1.0), 2)} | {scaling} | '
                f'{100 * row["kept"]:.0f} % | {seams} | '
                f'{row["path_1s_m"]:.1f} / {row["true_path_1s_m"]:.1f} m | '
                f'{row["pos_1s_cm"]:.1f} / {row["yaw_1s_mrad"]:.1f} | '
                f'{row.get("self_check", "")} |')
    return '\n'.join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--duration', type=float, default=60.0, help='s per scene')
    parser.add_argument('--chunk-s', type=float, default=20.0, help='chunk length (s)')
    parser.add_argument('--scenes', nargs='+', default=list(SCENES), choices=SCENES)
    parser.add_argument('--seed', type=int, default=5)
    parser.add_argument('--jobs-list', type=int, nargs='+', default=[2, 1], metavar='N',
                        help='processes of the after runs (the first is also the before run '
                        'and the reference of the identical-poses check); e.g. 1 2 4 8 16')
    parser.add_argument('--repeat', type=int, default=1,
                        help='runs of every contender; the median wall and CPU time is kept')
    parser.add_argument('--no-before', action='store_true',
                        help='skip the run without the self-check')
    parser.add_argument('--variant', action='append', default=[], metavar='LABEL=ARGS',
                        help='one more contender: the first of --jobs-list with these extra '
                        'groundtruth arguments, e.g. stride2="--stride 2" (repeatable)')
    parser.add_argument('--old', type=Path, metavar='DIR',
                        help='also run the skidkin_ros found in DIR (e.g. /work/main, or a '
                        '`git archive` of an older commit) with every --jobs-list N, as old_jN')
    parser.add_argument('--no-kiss', action='store_true',
                        help='skip plain kiss_icp_pipeline (compare ours with --old only)')
    parser.add_argument('--json', type=Path, help='also write the results here')
    args = parser.parse_args(argv)
    variants = []
    for text in args.variant:
        label, _, extra = text.partition('=')
        if not label or not extra:
            parser.error(f'--variant wants LABEL=ARGS, got {text!r}')
        variants.append((label, extra.split()))
    counted = _adopt_orphans()
    print(f'  load average {load_average()}; CPU of pool workers '
          f'{"counted" if counted else "NOT counted (no subreaper)"}', flush=True)
    results = []
    with tempfile.TemporaryDirectory(prefix='gt_scenes_') as tmp:
        for scene in args.scenes:
            print(f'  {scene}: {args.duration:g} s', flush=True)
            results.append(run_scene(scene, args.duration, args.seed, Path(tmp), args.chunk_s,
                                     args.jobs_list, args.repeat, not args.no_before,
                                     variants, args.old, not args.no_kiss))
    print(table(results))
    print(json.dumps(results, indent=1, default=float))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=float))
    return 0


if __name__ == '__main__':
    sys.exit(main())
