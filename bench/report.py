"""Render the benchmark results: the Markdown tables (results.md) and the cost plot."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

from skidkin_ros.atomic import atomic_write_text

LATENCY_GOAL = 1.2
RATE_GOAL_HZ = 1000.0
CALIB_2KM_GOAL_S = 5.0
SMOKE_NOTE = 'smoke run: tiny sizes, numbers not meaningful'


def _num(value: Any, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return 'n/a'
    return f'{value:.{digits}f}'


def _step(sut: Mapping[str, Any], rate_hz: float) -> Mapping[str, Any] | None:
    for step in sut['steps']:
        if step['rate_hz'] == rate_hz and not step.get('ladder'):
            return step
    return None


def node_rows(node: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Return one summary row per SUT with the ratios against the mean relay."""
    relays = [s for s in node['suts'] if s['kind'] == 'relay' and not s['error']]
    base = {}
    for rate in (100.0, 1000.0):
        values = [_step(s, rate)['p50_latency_us'] for s in relays if _step(s, rate)]
        base[rate] = sum(values) / len(values) if values else math.nan
    rows = []
    for sut in node['suts']:
        row: dict[str, Any] = {'label': sut['label'], 'error': sut['error']}
        for rate, key in ((100.0, '100'), (1000.0, '1k')):
            step = _step(sut, rate)
            row[f'p50_{key}'] = step['p50_latency_us'] if step else math.nan
            row[f'p99_{key}'] = step['p99_latency_us'] if step else math.nan
            row[f'drop_{key}'] = f'{step["dropped"]}/{step["sent"]}' if step else 'n/a'
            row[f'cpu_{key}'] = step['cpu_us_per_msg'] if step else math.nan
            row[f'ratio_{key}'] = row[f'p50_{key}'] / base[rate] if base[rate] else math.nan
        row['max_held_hz'] = sut['max_held_hz']
        rows.append(row)
    return rows


def _node_section(node: Mapping[str, Any]) -> list[str]:
    lines = ['## Node: JointState -> Odometry, against a bare rclpy relay', '',
             f'Latency ratio = p50 / mean p50 of the relay runs at the same rate (goal <= '
             f'{LATENCY_GOAL}); max held = highest paced rate losing <= 0.1 % of the '
             f'messages (goal >= {RATE_GOAL_HZ:.0f} Hz; ladder {node["ladder_hz"]}); CPU = SUT '
             'process CPU time (all threads) / messages sent. SUT pinned to one core, driver on '
             'another.', '',
             '| SUT | p50 µs 100 Hz | p99 µs 100 Hz | ratio 100 Hz | p50 µs 1 kHz | '
             'p99 µs 1 kHz | ratio 1 kHz | dropped 1 kHz | CPU µs/msg 100 Hz | '
             'CPU µs/msg 1 kHz | max held Hz |',
             '|---|---|---|---|---|---|---|---|---|---|---|']
    for row in node_rows(node):
        if row['error']:
            lines.append(f'| {row["label"]} | failed: {row["error"]} |' + ' |' * 10)
            continue
        lines.append(
            f'| {row["label"]} | {_num(row["p50_100"], 0)} | {_num(row["p99_100"], 0)} | '
            f'{_num(row["ratio_100"], 2)} | {_num(row["p50_1k"], 0)} | '
            f'{_num(row["p99_1k"], 0)} | {_num(row["ratio_1k"], 2)} | {row["drop_1k"]} | '
            f'{_num(row["cpu_100"], 0)} | {_num(row["cpu_1k"], 0)} | '
            f'{_num(row["max_held_hz"], 0)} |')
    for label, reason in node.get('not_run', {}).items():
        lines.append(f'| {label} | {reason} |' + ' |' * 10)
    return lines + ['']


def _calib_section(calib: Mapping[str, Any]) -> list[str]:
    lines = ['## Calibration (all five models) against the distance driven', '',
             'Simulated drives without lidar, `calibrate()` with default options (segments, '
             'fits, hold-out evaluation, noise); fit = time inside the five fits. '
             f'Goal: 2 km in < {CALIB_2KM_GOAL_S:g} s; linear growth (flat s/km). '
             f'Multi-start fits: {calib.get("n_starts", "default")} starts.', '',
             '| km | wheel samples | train segments | calibrate s | fit s | other s | s/km |',
             '|---|---|---|---|---|---|---|']
    for r in calib['rows']:
        lines.append(f'| {r["km"]:.2f} | {r["wheel_samples"]} | {r["train_segments"]} | '
                     f'{r["calibrate_s"]:.2f} | {r["fit_s"]:.2f} | {r["other_s"]:.2f} | '
                     f'{r["s_per_km"]:.2f} |')
    lines += ['', f's/km largest / smallest size: '
              f'{_num(calib["per_km_ratio_largest_smallest"], 2)} (1.0 = linear; < 1: a fixed '
              'cost is amortised).', '']
    if calib['rows']:
        biggest = calib['rows'][-1]
        split = ', '.join(f'{name} {s:.2f} s' for name, s in biggest['fit_s_by_model'].items())
        lines += [f'Fit time by model at {biggest["km"]:.2f} km: {split}.', '']
    return lines


def _lidar_section(lidar: Mapping[str, Any]) -> list[str]:
    lines = ['## Lidar pipeline (simulated 16-ring lidar at 10 Hz, '
             f'{lidar["azimuth_resolution_deg"]:g} deg azimuth)', '',
             'Read = wheels + extrinsic + all clouds from the bag; ICP = kiss-icp on frames '
             'already in memory; fit = five models on segments of the ICP truth. Real-time '
             'factor = recording duration / (read + ICP + fit). Peak memory: a fresh '
             'interpreter running the streaming pipeline of the CLI (load_source with ICP).', '',
             '| frames | points/frame | bag MB | read ms/frame | ICP ms/frame | fit s | '
             'real-time factor | ICP-only RTF | peak MB | MB above imports |',
             '|---|---|---|---|---|---|---|---|---|---|']
    for r in lidar['rows']:
        mem = r['memory']
        fit = _num(r['fit_s'], 2) + (' (too few segments)' if r['fit_error'] else '')
        lines.append(
            f'| {r["frames"]} | {r["points_per_frame"]:.0f} | {r["bag_mb"]:.1f} | '
            f'{r["read_ms_per_frame"]:.2f} | {r["icp_ms_per_frame"]:.1f} | {fit} | '
            f'{r["real_time_factor"]:.1f} | {r["icp_real_time_factor"]:.1f} | '
            f'{_num(mem.get("peak_mb"), 0)} | {_num(mem.get("pipeline_mb"), 0)} |')
    return lines + ['']


def _diag_section(diag: Mapping[str, Any]) -> list[str]:
    lines = ['## Diagnosis against the distance driven', '']
    if not diag['available']:
        return lines + [f'diagnosis: {diag["reason"]}', '']
    lines += ['| km | drives | diagnose s | s/km | extensions accepted |', '|---|---|---|---|---|']
    for r in diag['rows']:
        accepted = ', '.join(r['accepted']) if r['accepted'] else 'none'
        lines.append(f'| {r["km"]:.2f} | {r["drives"]} | {r["diagnose_s"]:.2f} | '
                     f'{r["s_per_km"]:.2f} | {accepted} |')
    return lines + ['']


def write_markdown(results: Mapping[str, Any], path: Path) -> None:
    """Write results.md: the command, the machine and one table per benchmark."""
    machine = results['machine']
    lines = ['# skidkin_ros benchmarks', '',
             f'Produced by `{results["command"]}` on {machine["date"]} '
             f'({SMOKE_NOTE if results["smoke"] else "full run"}'
             f'; {results["elapsed_s"]:.0f} s). Machine: {machine["cpus"]} CPU(s) '
             f'({machine["cpu_model"]}), Python {machine["python"]}, {machine["platform"]}, '
             f'RMW {machine["rmw"]}, load average at start {machine["loadavg"]}.', '',
             'Absolute times depend on the machine and its load; the ratios (node/relay, '
             'time per km across sizes) are measured in the same run and are the numbers to '
             'compare.', '']
    lines += _node_section(results['node'])
    lines += _calib_section(results['calibration'])
    lines += _lidar_section(results['lidar'])
    lines += _diag_section(results['diagnosis'])
    atomic_write_text(path, '\n'.join(lines), force=True)


def write_plot(results: Mapping[str, Any], path: Path) -> None:
    """Write cost_vs_size.png: calibration time vs km, lidar read/ICP time vs frames."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    calib = results['calibration']['rows']
    if calib:
        km = [r['km'] for r in calib]
        left.plot(km, [r['calibrate_s'] for r in calib], 'o-', label='calibrate (total)')
        left.plot(km, [r['fit_s'] for r in calib], 's--', label='five fits')
    diag = results['diagnosis']
    if diag['available'] and diag['rows']:
        left.plot([r['km'] for r in diag['rows']], [r['diagnose_s'] for r in diag['rows']],
                  '^-.', label='diagnose')
    left.set_xlabel('distance driven (km)')
    left.set_ylabel('time (s)')
    left.set_title('Calibration cost')
    left.grid(True, alpha=0.3)
    left.legend()
    lidar = results['lidar']['rows']
    if lidar:
        frames = [r['frames'] for r in lidar]
        right.plot(frames, [r['icp_s'] for r in lidar], 'o-', label='kiss-icp')
        right.plot(frames, [r['read_s'] for r in lidar], 's--', label='bag reading')
        right.plot(frames, [r['fit_s'] for r in lidar], '^-.', label='fitting')
    right.set_xlabel('lidar frames')
    right.set_ylabel('time (s)')
    right.set_title('Lidar pipeline cost')
    right.grid(True, alpha=0.3)
    right.legend()
    fig.tight_layout()
    tmp = path.with_name(path.name + '.tmp.png')
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(path)
