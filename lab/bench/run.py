"""Run every skidkin_ros benchmark in one go and write results.json, results.md and a plot.

Examples::

    python lab/bench/run.py --out lab/bench/results  # full run (make bench), a few minutes
    python lab/bench/run.py --smoke --out /tmp/bench  # tiny sizes, seconds (CI, make bench-smoke)
    python lab/bench/run.py --out /tmp/bench --only node   # one part (node, calibration, lidar,
                                                       # groundtruth, diagnosis, heading); the
                                                       # others are left empty

Parts: the odometry node against a bare relay (lab/bench/node_bench.py), calibration time against
distance (calib_bench.py), the lidar pipeline (lidar_bench.py), the ground truth on the outdoor
scene against kiss_icp_pipeline and the kiss-icp settings table (gt_bench.py, icp_settings.py),
the diagnosis (diag_bench.py), heading at window ends on the Husky against a plain window-end
fit (heading_bench.py), and position and heading at window ends on the Husky and a Warthog-like
simulation, the written model beside its plain window-end fit (segments_bench.py). Absolute
numbers depend on the machine and its load; ratios measured in
the same run are what to compare.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
import datetime
import json
import logging
import math
import os
from pathlib import Path
import platform
import sys
import tempfile
import time
from typing import Any, Mapping, Sequence

import calib_bench
import diag_bench
import diag_speed
import gt_bench
import heading_bench
import icp_settings
import lidar_bench
import node_bench
import report
import segments_bench
from skidkin_ros.atomic import atomic_write_text
from skidkin_ros.core.kinematics.models import MODEL_NAMES
from skidkin_ros.core.parallel import one_blas_thread, usable_cpus

PARTS = ('node', 'calibration', 'lidar', 'groundtruth', 'diagnosis', 'heading', 'segments')


@dataclass(frozen=True)
class Sizes:
    """Everything that differs between the full and the smoke run."""

    node_plan: tuple[tuple[float, float], ...]
    node_ladder_hz: tuple[float, ...]
    node_ladder_s: float
    node_rounds: int
    node_models: tuple[str, ...]
    node_augmented: bool
    calib_km: tuple[float, ...]
    calib_drive_s: float
    holdout_block_s: float
    calib_n_starts: int | None
    lidar_durations_s: tuple[float, ...]
    lidar_azimuth_deg: float
    lidar_horizon_m: float
    diag_km: tuple[float, ...]
    diag_drive_s: float
    diag_speed_km: float
    gt_outdoor_s: float
    gt_drive_s: float
    gt_why_frames: int
    icp_settings_s: float


FULL = Sizes(
    node_plan=((100.0, 6.0), (1000.0, 6.0)),
    node_ladder_hz=(1500.0, 2000.0, 2500.0, 3000.0, 4000.0, 5000.0, 6000.0),
    node_ladder_s=1.5, node_rounds=12, node_models=MODEL_NAMES, node_augmented=True,
    calib_km=(0.5, 1.0, 2.0, 4.0), calib_drive_s=600.0, holdout_block_s=60.0,
    calib_n_starts=None,
    lidar_durations_s=(20.0, 40.0, 80.0), lidar_azimuth_deg=0.5, lidar_horizon_m=2.0,
    diag_km=(0.05, 0.1, 0.2), diag_drive_s=60.0, diag_speed_km=0.5,
    gt_outdoor_s=300.0, gt_drive_s=600.0, gt_why_frames=300, icp_settings_s=60.0)
SMOKE = Sizes(
    node_plan=((100.0, 0.5), (1000.0, 0.5)), node_ladder_hz=(), node_ladder_s=0.3, node_rounds=1,
    node_models=('full_linear',), node_augmented=False,
    calib_km=(0.02, 0.04), calib_drive_s=40.0, holdout_block_s=10.0, calib_n_starts=1,
    lidar_durations_s=(3.0, 5.0), lidar_azimuth_deg=4.0, lidar_horizon_m=0.5,
    diag_km=(0.03,), diag_drive_s=40.0, diag_speed_km=0.03,
    gt_outdoor_s=12.0, gt_drive_s=80.0, gt_why_frames=20, icp_settings_s=4.0)


def machine_facts() -> dict[str, Any]:
    """Return what the numbers depend on: CPUs, Python, platform, RMW, load, date."""
    cpu_model = 'unknown'
    try:
        with open('/proc/cpuinfo', encoding='utf-8') as stream:
            for line in stream:
                if line.startswith('model name'):
                    cpu_model = line.split(':', 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        from rclpy.utilities import get_rmw_implementation_identifier
        rmw = get_rmw_implementation_identifier()
    except (ImportError, RuntimeError):
        rmw = os.environ.get('RMW_IMPLEMENTATION', 'unknown')
    load = os.getloadavg() if hasattr(os, 'getloadavg') else (math.nan,) * 3
    return {
        'cpus': os.cpu_count(), 'cpu_model': cpu_model, 'python': platform.python_version(),
        'platform': platform.platform(), 'rmw': rmw,
        'loadavg': ' '.join(f'{v:.2f}' for v in load),
        'date': datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC'),
    }


def _sut_result(kind: str, label: str, params: Mapping[str, str] | None) -> dict[str, Any]:
    return {'kind': kind, 'label': label, 'params': dict(params or {}), 'steps': [],
            'reference_steps': [], 'error': None, 'max_held_hz': 0.0, 'stderr_tail': []}


def _finish(result: dict[str, Any]) -> dict[str, Any]:
    held_rates = [s['achieved_hz'] for s in result['steps'] if node_bench.held(s)]
    result['max_held_hz'] = max(held_rates, default=0.0)
    return result


def run_node(sizes: Sizes, domain_id: int, smoke: bool) -> dict[str, Any]:
    """Measure every node model paired with one bare relay, then each one's rate ladder.

    The relay runs for the whole benchmark; each node SUT starts in turn and alternates with it
    in short blocks (node_bench.paired_steps), so each latency ratio compares runs made under
    the same machine conditions.
    """
    suts: list[tuple[str, str, dict[str, str] | None]] = [
        ('relay_serialized', node_bench.SERIALIZED_RELAY_LABEL, None)]
    suts += [('odom', f'odom_node {model}', {'model': model}) for model in sizes.node_models]
    if not smoke:  # the covariance propagation of a calibrated parameters file, per sample
        label, params = node_bench.CALIBRATED_CASE
        suts.append(('odom', f'odom_node {label}', params))
    not_run = {}
    if sizes.node_augmented:
        label, params = node_bench.augmented_params()
        suts.append(('odom', f'odom_node {label}', params))
    if smoke:
        for model in MODEL_NAMES:
            if model not in sizes.node_models:
                not_run[f'odom_node {model}'] = 'not run in the smoke run'
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else []
    sut_cpu = node_bench.pin_driver(cpus)
    relay_result = _sut_result('relay', 'bare rclpy relay', None)
    results = [relay_result]
    try:
        relay = node_bench.Sut('relay', relay_result['label'], None, domain_id, sut_cpu)
    except RuntimeError as err:
        relay_result['error'] = str(err)
        return {'suts': results, 'not_run': not_run, 'ladder_hz': list(sizes.node_ladder_hz),
                'plan': [list(step) for step in sizes.node_plan], 'domain_id': domain_id,
                'rounds': sizes.node_rounds}
    try:
        for kind, label, params in suts:
            print(f'  node: {label} (paired with the relay)', flush=True)
            result = _sut_result(kind, label, params)
            results.append(result)
            try:
                sut = node_bench.Sut(kind, label, params, domain_id, sut_cpu)
            except RuntimeError as err:
                result['error'] = str(err)
                continue
            try:
                result['steps'], result['reference_steps'] = node_bench.paired_steps(
                    relay, sut, sizes.node_plan, sizes.node_rounds)
                relay_result['steps'] += result['reference_steps']
                result['steps'] += sut.ladder(sizes.node_ladder_hz, sizes.node_ladder_s)
            except RuntimeError as err:
                result['error'] = str(err)
            finally:
                tail = sut.close()
                if result['error']:
                    result['stderr_tail'] = tail
            _finish(result)
        print('  node: bare rclpy relay (ladder)', flush=True)
        relay_result['steps'] += relay.ladder(sizes.node_ladder_hz, sizes.node_ladder_s)
    finally:
        relay.close()
        if cpus and hasattr(os, 'sched_setaffinity'):
            os.sched_setaffinity(0, set(cpus))
    _finish(relay_result)
    return {'suts': results, 'not_run': not_run, 'ladder_hz': list(sizes.node_ladder_hz),
            'plan': [list(step) for step in sizes.node_plan], 'domain_id': domain_id,
            'rounds': sizes.node_rounds}


def _empty(part: str) -> dict[str, Any]:
    if part == 'node':
        return {'suts': [], 'not_run': {}, 'ladder_hz': [], 'plan': []}
    if part == 'segments':
        return {'rows': []}
    if part in ('diagnosis', 'heading'):
        return {'available': False, 'reason': 'not run (--only)', 'rows': []}
    if part == 'lidar':
        return {'rows': [], 'azimuth_resolution_deg': math.nan, 'horizon_m': math.nan}
    if part == 'groundtruth':
        return {'available': False, 'reason': 'not run (--only)'}
    return {'rows': [], 'per_km_ratio_largest_smallest': math.nan}


def run_all(out: Path, smoke: bool, parts: Sequence[str], domain_id: int,
            command: str, overrides: Mapping[str, float] | None = None,
            diag_old: Sequence[str] = ()) -> dict[str, Any]:
    """Run the requested parts and write results.json, results.md and cost_vs_size.png."""
    sizes = dataclasses.replace(SMOKE if smoke else FULL, **dict(overrides or {}))
    tic = time.perf_counter()
    results: dict[str, Any] = {'command': command, 'smoke': smoke, 'machine': machine_facts()}
    results.update({part: _empty(part) for part in PARTS})
    if 'node' in parts:
        print('node benchmark', flush=True)
        results['node'] = run_node(sizes, domain_id, smoke)
    if 'calibration' in parts:
        print('calibration benchmark', flush=True)
        results['calibration'] = calib_bench.run(sizes.calib_km, sizes.calib_drive_s,
                                                 sizes.holdout_block_s, sizes.calib_n_starts)
    if 'lidar' in parts:
        print('lidar benchmark', flush=True)
        with tempfile.TemporaryDirectory(prefix='skidkin_bench_') as folder:
            results['lidar'] = lidar_bench.run(Path(folder), sizes.lidar_durations_s,
                                               sizes.lidar_azimuth_deg, sizes.lidar_horizon_m)
    if 'groundtruth' in parts:
        print('ground-truth benchmark (outdoor scene, kiss_icp_pipeline, settings)', flush=True)
        with tempfile.TemporaryDirectory(prefix='skidkin_gt_') as folder:
            gt = gt_bench.run(Path(folder), sizes.gt_outdoor_s, sizes.gt_drive_s,
                              sizes.gt_why_frames, usable_cpus())
        gt['settings'] = icp_settings.run(sizes.icp_settings_s)
        gt['available'] = True
        results['groundtruth'] = gt
    if 'diagnosis' in parts:
        print('diagnosis benchmark', flush=True)
        if sizes.diag_km:
            results['diagnosis'] = diag_bench.run(sizes.diag_km, sizes.diag_drive_s,
                                                  min(sizes.holdout_block_s, 20.0))
        else:
            results['diagnosis'] = {'available': False, 'rows': [],
                                    'reason': 'not run in the smoke run (too slow for CI)'}
        print('diagnosis speed: exact against finite-difference Jacobians'
              + (f' and {", ".join(diag_old)}' if diag_old else ''), flush=True)
        olds = [Path(old) for old in diag_old if Path(old).is_dir()]
        commits = [old for old in diag_old if not Path(old).is_dir()]
        results['diagnosis']['speed'] = diag_speed.compare(
            sizes.diag_speed_km, min(2, usable_cpus()), olds, True, commits)
    if 'heading' in parts:
        print('heading benchmark (Husky, plain window-end reference)', flush=True)
        results['heading'] = heading_bench.run()
    if 'segments' in parts:
        print('window ends on the Husky and a Warthog-like simulation (written vs plain)',
              flush=True)
        results['segments'] = (segments_bench.run(('rotation',), sim_steps=30) if smoke
                               else segments_bench.run())
    results['elapsed_s'] = time.perf_counter() - tic
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / 'results.json', json.dumps(results, indent=1, default=str),
                      force=True)
    report.write_markdown(results, out / 'results.md')
    report.write_plot(results, out / 'cost_vs_size.png')
    return results


def main(argv: Sequence[str] | None = None) -> int:
    """Parse the command line and run the benchmarks; return the exit code."""
    parser = argparse.ArgumentParser(
        description='Benchmark the skidkin_ros node, calibration, lidar pipeline and '
        'diagnosis; write results.json, results.md and cost_vs_size.png.',
        formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split('\n\n')[1])
    parser.add_argument('--out', type=Path, default=Path('lab/bench/results'),
                        help='output folder (default: lab/bench/results)')
    parser.add_argument('--smoke', action='store_true',
                        help='tiny sizes: checks that everything runs, in seconds')
    parser.add_argument('--only', nargs='+', choices=PARTS, default=list(PARTS),
                        help='run only these parts')
    parser.add_argument('--domain-id', type=int, default=None,
                        help='ROS domain of the node benchmark (default: from the process id, '
                        'away from domain 0)')
    parser.add_argument('--outdoor-s', type=float, metavar='S',
                        help='ground truth: seconds of the outdoor drive run side by side with '
                        'kiss_icp_pipeline (full run: 300)')
    parser.add_argument('--drive-s', type=float, metavar='S',
                        help='ground truth: seconds of the drive calibrated from the bag (full '
                        'run: 600)')
    parser.add_argument('--settings-s', type=float, metavar='S',
                        help='seconds per scene of the kiss-icp settings table (full run: 60)')
    parser.add_argument('--diag-old', action='append', default=[], metavar='OLD',
                        help='diagnosis speed: also time an older checkout (a folder) or a '
                        'commit of this repository, e.g. the one an issue measured (repeatable)')
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    domain_id = args.domain_id if args.domain_id is not None else 40 + os.getpid() % 60
    command = 'python lab/bench/run.py ' + ' '.join(sys.argv[1:] if argv is None else argv)
    overrides = {name: value for name, value in (('gt_outdoor_s', args.outdoor_s),
                                                 ('gt_drive_s', args.drive_s),
                                                 ('icp_settings_s', args.settings_s))
                 if value is not None}
    with one_blas_thread():  # as the CLI runs (core.parallel); calib_bench compares both
        results = run_all(args.out, args.smoke, args.only, domain_id, command.strip(), overrides,
                          args.diag_old)
    print(f'wrote {args.out / "results.md"} in {results["elapsed_s"]:.0f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
