"""Render the benchmark results: the Markdown tables (results.md) and the cost plot."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import segments_bench
from skidkin_ros.atomic import atomic_write_text

LATENCY_GOAL = 1.2
RATE_GOAL_HZ = 1000.0
CALIB_2KM_GOAL_S = 5.0
GT_RTF_GOAL = 4.0
GT_SPEEDUP_GOAL = 2.0
GT_DRIVE_GOAL_S = 180.0
SMOKE_NOTE = 'smoke run: tiny sizes, numbers not meaningful'


def _num(value: Any, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return 'n/a'
    return f'{value:.{digits}f}'


def _median(values: Sequence[float]) -> float:
    finite = sorted(v for v in values if isinstance(v, (int, float)) and math.isfinite(v))
    if not finite:
        return math.nan
    mid = len(finite) // 2
    return finite[mid] if len(finite) % 2 else 0.5 * (finite[mid - 1] + finite[mid])


def _at(steps: Sequence[Mapping[str, Any]], rate_hz: float) -> list[Mapping[str, Any]]:
    return [s for s in steps if s['rate_hz'] == rate_hz and not s.get('ladder')]


def node_rows(node: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Return one summary row per SUT: medians over its rounds and the paired ratios.

    A node's latency ratio at a rate is the median, over rounds, of its p50 divided by the p50
    of the relay block run next to it; its CPU ratio compares the mean CPU per message of the
    same blocks. The relay row pools every block it ran (ratio 1 by definition).
    """
    rows = []
    for sut in node['suts']:
        row: dict[str, Any] = {'label': sut['label'], 'error': sut['error'],
                               'reference': sut['kind'] == 'relay'}
        for rate, key in ((100.0, '100'), (1000.0, '1k')):
            mine = _at(sut['steps'], rate)
            refs = {s['round']: s for s in _at(sut.get('reference_steps', []), rate)}
            row[f'p50_{key}'] = _median([s['p50_latency_us'] for s in mine])
            row[f'p99_{key}'] = _median([s['p99_latency_us'] for s in mine])
            row[f'drop_{key}'] = (f'{sum(s["dropped"] for s in mine)}/'
                                  f'{sum(s["sent"] for s in mine)}' if mine else 'n/a')
            cpu = [s['cpu_us_per_msg'] for s in mine]
            row[f'cpu_{key}'] = sum(cpu) / len(cpu) if cpu else math.nan
            pairs = [(s, refs[s['round']]) for s in mine if s.get('round') in refs]
            row[f'ratio_{key}'] = (1.0 if row['reference'] else _median(
                [s['p50_latency_us'] / r['p50_latency_us'] for s, r in pairs
                 if r['p50_latency_us'] > 0]))
            ref_cpu = [r['cpu_us_per_msg'] for _, r in pairs]
            row[f'cpu_ratio_{key}'] = (1.0 if row['reference'] else
                                       row[f'cpu_{key}'] / (sum(ref_cpu) / len(ref_cpu))
                                       if ref_cpu and sum(ref_cpu) > 0 else math.nan)
        row['max_held_hz'] = sut['max_held_hz']
        rows.append(row)
    return rows


def _node_section(node: Mapping[str, Any]) -> list[str]:
    rounds = node.get('rounds', 1)
    lines = ['## Node: JointState -> Odometry, against a bare rclpy relay', '',
             'The relay runs for the whole benchmark; each node alternates with it in '
             f'{rounds} short blocks per rate (relay, node, node, relay, ...), so both see the '
             'same machine at the same time. Latency ratio = median over the blocks of node '
             f'p50 / relay p50 of the paired block (goal <= {LATENCY_GOAL}); p50 and p99 = '
             'median over the blocks; CPU = SUT process CPU time (all threads) / messages '
             'sent, and its ratio to the paired relay blocks; max held = highest paced rate at '
             'which one block or ladder step lost <= 0.1 % of the messages (goal >= '
             f'{RATE_GOAL_HZ:.0f} Hz; ladder {node["ladder_hz"]}). SUTs pinned to one core, '
             'driver on the other. The serialized relay is paired like a node: it takes the '
             'JointState serialized and publishes a pre-serialized Odometry, converting no '
             'message (the floor of rclpy); the node also reads and writes serialized messages.',
             '',
             '| SUT | p50 µs 100 Hz | ratio 100 Hz | p50 µs 1 kHz | p99 µs 1 kHz | '
             'ratio 1 kHz | dropped 1 kHz | CPU µs/msg 1 kHz | CPU ratio 1 kHz | '
             'max held Hz |',
             '|---|---|---|---|---|---|---|---|---|---|']
    for row in node_rows(node):
        if row['error']:
            lines.append(f'| {row["label"]} | failed: {row["error"]} |' + ' |' * 8)
            continue
        ratio = ('reference' if row['reference'] else _num(row['ratio_100'], 2),
                 'reference' if row['reference'] else _num(row['ratio_1k'], 2),
                 'reference' if row['reference'] else _num(row['cpu_ratio_1k'], 2))
        lines.append(
            f'| {row["label"]} | {_num(row["p50_100"], 0)} | {ratio[0]} | '
            f'{_num(row["p50_1k"], 0)} | {_num(row["p99_1k"], 0)} | {ratio[1]} | '
            f'{row["drop_1k"]} | {_num(row["cpu_1k"], 0)} | {ratio[2]} | '
            f'{_num(row["max_held_hz"], 0)} |')
    for label, reason in node.get('not_run', {}).items():
        lines.append(f'| {label} | {reason} |' + ' |' * 8)
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
    blas = calib.get('blas')
    if blas:
        lines += [f'BLAS threads (the smallest size, calibrated twice): '
                  f'{blas["all_threads_s"]:.2f} s with {blas["threads"]} BLAS threads, '
                  f'{blas["one_thread_s"]:.2f} s with one '
                  f'(what the CLI uses, `core.parallel.one_blas_thread`): ratio '
                  f'{blas["ratio"]:.2f}.', '']
    speed = calib.get('before_after')
    if speed:
        lines += [f'`skidkin calibrate` of {speed["km"]:g} km, the earlier path and today\'s in '
                  f'the same run (calib_speed.py, {speed["rounds"]} round(s), '
                  f'{speed["cpus"]} CPUs, each in a fresh process; wall / process CPU '
                  f'seconds): earlier {speed["earlier_s"]:.2f} / '
                  f'{speed.get("earlier_cpu_s", math.nan):.2f} s, today '
                  f'{speed["today_s"]:.2f} / {speed.get("today_cpu_s", math.nan):.2f} s '
                  f'(fits {speed["fit_s_today"]:.2f} s): {speed["ratio"]:.2f}x faster; same '
                  f'written model and values: {"yes" if speed["same_result"] else "NO"}.', '']
        if 'issue_s' in speed:
            lines += [f'The issue-time code ({speed["issue_code"]}, its own defaults) in the same '
                      f'run: {speed["issue_s"]:.2f} / {speed["issue_cpu_s"]:.2f} s, '
                      f'{speed["issue_ratio"]:.2f}x today\'s wall time, '
                      f'{speed["issue_cpu_ratio"]:.2f}x its CPU time. Goal: at most 8 s on '
                      '2 cores (a quiet machine).', '']
        elif speed.get('issue_error'):
            lines += [f'The issue-time code did not run: {speed["issue_error"]}', '']
    return lines


def _lidar_section(lidar: Mapping[str, Any]) -> list[str]:
    lines = ['## Lidar pipeline (simulated 16-ring lidar at 10 Hz)', '',
             'Read = wheels + extrinsic + all clouds from the bag; ICP = kiss-icp on frames '
             'already in memory; fit = five models on segments of the ICP truth. Real-time '
             'factor = recording duration / (read + ICP + fit). Peak memory: a fresh '
             'interpreter running the streaming pipeline of the CLI (load_source with ICP).', '',
             '| scene | frames | points/frame | bag MB | read ms/frame | ICP ms/frame | fit s | '
             'real-time factor | ICP-only RTF | peak MB | MB above imports |',
             '|---|---|---|---|---|---|---|---|---|---|---|']
    for r in lidar['rows']:
        mem = r['memory']
        fit = _num(r['fit_s'], 2) + (' (too few segments)' if r['fit_error'] else '')
        lines.append(
            f'| {r.get("scene", "courtyard")} | {r["frames"]} | {r["points_per_frame"]:.0f} | '
            f'{r["bag_mb"]:.1f} | '
            f'{r["read_ms_per_frame"]:.2f} | {r["icp_ms_per_frame"]:.1f} | {fit} | '
            f'{r["real_time_factor"]:.1f} | {r["icp_real_time_factor"]:.1f} | '
            f'{_num(mem.get("peak_mb"), 0)} | {_num(mem.get("pipeline_mb"), 0)} |')
    return lines + ['']


def _cm(value: Any) -> str:
    return _num(100.0 * value, 2) if isinstance(value, (int, float)) else 'n/a'


def _mrad(value: Any) -> str:
    return _num(1e3 * value, 2) if isinstance(value, (int, float)) else 'n/a'


def _gt_section(gt: Mapping[str, Any]) -> list[str]:
    import icp_settings

    lines = ['## Ground truth on the outdoor scene', '']
    if not gt.get('available'):
        return lines + [f'ground truth: {gt.get("reason", "not run")}', '']
    side = gt['side_by_side']
    lines += [f'Simulated outdoor drive of {gt["outdoor_s"]:g} s: an open field with 400 trees, '
              'a flat ground, a VLP-16-like lidar (16 rings, 360 columns, 10 Hz, '
              f'{gt["points_per_frame"]:.0f} points per scan, per-point times, base -> lidar on '
              "/tf_static). `kiss_icp_pipeline --topic /points BAG` (kiss-icp's own tool, its "
              'defaults, every core) and `skidkin groundtruth BAG --no-cache --jobs '
              f'{gt["jobs"]}` run as subprocesses in the order kiss, skidkin, skidkin, kiss. '
              'Errors: median over every 1 s and every 2 m increment against the '
              "simulator's truth.", '']
    if side.get('error'):
        lines += [f'side by side failed: {side["error"]}', '']
    else:
        lines += ['| tool | wall s (each run) | real-time factor | 1 s: cm | 1 s: mrad | '
                  '2 m: cm | 2 m: mrad |', '|---|---|---|---|---|---|---|']
        for who, label, rtf in (('kiss', 'kiss_icp_pipeline', side['kiss_rtf']),
                                ('skidkin', 'skidkin groundtruth', side['skidkin_rtf'])):
            err = side['errors'][who]
            seconds = ', '.join(f'{v:.1f}' for v in side[f'{who}_s'])
            lines.append(f'| {label} | {seconds} | {rtf:.1f} | {_cm(err["pos_1s_m"])} | '
                         f'{_mrad(err["yaw_1s_rad"])} | {_cm(err["pos_2m_m"])} | '
                         f'{_mrad(err["yaw_2m_rad"])} |')
        lines += ['', f'skidkin groundtruth is **{side["speedup"]:.2f}x** faster than '
                  f'kiss_icp_pipeline (goal >= {GT_SPEEDUP_GOAL:g}) at a real-time factor of '
                  f'**{side["skidkin_rtf"]:.1f}** (goal >= {GT_RTF_GOAL:g}); '
                  f'{100 * side["errors"]["skidkin"]["valid_share"]:.1f} % of its poses kept '
                  'by the guard.', '']
    why = gt['why']
    lines += [f'Why it was slower: each difference alone, on the first {why["frames"]} scans '
              'in memory, kiss-icp on one thread (CPU ms per scan):', '',
              '| what | CPU ms/scan | 1 s: cm | 1 s: mrad | 2 m: cm | 2 m: mrad |',
              '|---|---|---|---|---|---|']
    for r in why['rows']:
        lines.append(f'| {r["what"]} | {r["cpu_ms"]:.1f} | {_cm(r.get("pos_1s_m"))} | '
                     f'{_mrad(r.get("yaw_1s_rad"))} | {_cm(r.get("pos_2m_m"))} | '
                     f'{_mrad(r.get("yaw_2m_rad"))} |')
    calib = gt['calibrate']
    state = ('parameters written' if calib['written']
             else f'no parameters file: {calib["error"] or "see the exit code"}')
    lines += ['', f'A {calib["duration_s"]:g} s outdoor drive from bag to parameters file '
              f'(`skidkin calibrate BAG --no-cache --jobs {gt["jobs"]}`): '
              f'**{calib["seconds"]:.0f} s** (goal < {GT_DRIVE_GOAL_S:g} s for 600 s), '
              f'exit code {calib["exit_code"]}, {state}.', '',
              '### kiss-icp settings: speed and accuracy', '',
              'One setting changed at a time from the defaults; kiss-icp on one thread; '
              '`python lab/bench/icp_settings.py` runs this table alone.', '']
    return lines + icp_settings.markdown(gt['settings'])


def _diag_speed_lines(speed: Mapping[str, Any] | None) -> list[str]:
    """Old and new diagnosis speed of one run (diag_speed.compare), as a table."""
    if not speed:
        return []
    new = speed['new']
    lines = [f'Diagnosis speed, one run, {new["km"]:.2f} km, the same drives and processes '
             f'(load average {speed["loadavg"]}): wall and process CPU time (workers included) '
             'per km; ratios old / new.', '',
             '| code | s/km | CPU s/km | wall ratio | CPU ratio | extensions found | eps_t |',
             '|---|---|---|---|---|---|---|',
             f'| this checkout (exact Jacobians) | {new["s_per_km"]:.1f} | '
             f'{new["cpu_s_per_km"]:.1f} | 1 | 1 | {", ".join(new["found"]) or "none"} | '
             f'{new["eps_t"]:.5f} |']
    for name, row in speed['old'].items():
        label = ('this checkout, finite-difference Jacobians' if name == 'finite_differences'
                 else name)
        lines.append(f'| {label} | {row["s_per_km"]:.1f} | {row["cpu_s_per_km"]:.1f} | '
                     f'{row["speedup_wall"]:.2f} | {row["speedup_cpu"]:.2f} | '
                     f'{", ".join(row["found"]) or "none"} | {row["eps_t"]:.5f} |')
    return lines + ['']


def _diag_section(diag: Mapping[str, Any]) -> list[str]:
    lines = ['## Diagnosis against the distance driven', '']
    lines += _diag_speed_lines(diag.get('speed'))
    if not diag['available']:
        return lines + [f'diagnosis: {diag["reason"]}', '']
    lines += ['| km | drives | 1 process s | s/km | processes | s | s/km | speed-up | '
              'same result | extensions accepted |', '|---|---|---|---|---|---|---|---|---|---|']
    for r in diag['rows']:
        accepted = ', '.join(r['accepted']) if r['accepted'] else 'none'
        lines.append(f'| {r["km"]:.2f} | {r["drives"]} | {r["serial_s"]:.2f} | '
                     f'{r["serial_s_per_km"]:.1f} | {r["jobs"]} | {r["diagnose_s"]:.2f} | '
                     f'{r["s_per_km"]:.1f} | {r["speedup"]:.2f} | '
                     f'{"yes" if r["same_result"] else "NO"} | {accepted} |')
    return lines + ['']


def _segments_section(segments: Mapping[str, Any]) -> list[str]:
    lines = ['## Held-out window ends: the written model beside its plain window-end fit', '']
    if not segments.get('rows'):
        return lines + ['Not run.', '']
    lines += ['Husky table and a simulated Warthog-like windowed recording, split by '
              '`calib_step`; median position (m) and heading (rad) errors at the ends of the '
              'held-out 2 s windows (segments_bench.py).', '',
              segments_bench.table(segments), '']
    return lines


def _heading_section(heading: Mapping[str, Any]) -> list[str]:
    lines = ['## Heading at window ends: calibrated against a plain window-end fit (Husky)', '']
    if not heading.get('available'):
        return lines + [f'Not run: {heading.get("reason", "unknown")}.', '']
    lines += [f'DRIVE Husky table, even `calib_step` trains, odd evaluates; '
              f'{heading["train_windows"]} training and {heading["eval_windows"]} held-out '
              'windows of 2 s. Calibrated: `calibrate()` defaults (weighting '
              f'{heading["weighting"]}, selection {heading["selection"]}). Plain window-end '
              'fit: the same model on the same training windows, window-end x, y, yaw '
              'residuals, unit weights, no trimming. Medians at the held-out window ends.', '',
              '| model | calibrated yaw rad | plain window-end fit yaw rad | calibrated '
              'position m | plain window-end fit position m |', '|---|---|---|---|---|']
    for r in heading['rows']:
        tag = ' (best)' if r['best'] else ''
        lines.append(f'| {r["model"]}{tag} | {r["calibrated_yaw_rad"]:.4f} | '
                     f'{r["plain_yaw_rad"]:.4f} | {r["calibrated_position_m"]:.4f} | '
                     f'{r["plain_position_m"]:.4f} |')
    verdict = heading.get('verdict') or {}
    if verdict:
        worse = 'not worse' if verdict['heading_not_worse'] else 'WORSE'
        within = 'within' if verdict['translation_within'] else 'NOT within'
        lines += ['', f'Check on the best model ({verdict["model"]}): heading at window ends '
                  f'{worse} than the plain window-end fit; position error '
                  f'{verdict["translation_ratio"]:.3f} x the reference ({within} 5 %).']
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
    lines += _gt_section(results.get('groundtruth', {'available': False}))
    lines += _diag_section(results['diagnosis'])
    lines += _heading_section(results.get('heading', {}))
    lines += _segments_section(results.get('segments', {}))
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
        km = [r['km'] for r in diag['rows']]
        left.plot(km, [r['serial_s'] for r in diag['rows']], '^-.', label='diagnose, 1 process')
        left.plot(km, [r['diagnose_s'] for r in diag['rows']], 'v:',
                  label=f'diagnose, {diag["rows"][0]["jobs"]} processes')
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
