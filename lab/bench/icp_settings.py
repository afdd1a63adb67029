"""The speed/accuracy table of the kiss-icp settings that matter for the ground truth.

Each row changes one setting from the defaults (skidkin_ros.adapters.lidar_gt.IcpConfig) and
registers the same simulated drive in memory with kiss-icp on one thread: CPU ms per scan (the
process's CPU time; the machine's load disturbs it less than wall time) and the ground truth's
own error against the simulator's truth, median over every 1 s and every 2 m increment
(position cm, yaw mrad). Two scenes: the outdoor field with 400 trees and a VLP-16-like lidar
at 1 deg (lab/bench/gt_bench.py), and the courtyard of the project's demo (walls, boxes, pillars;
0.5 deg). The defaults are chosen from this table (docs/benchmarks.md, "Ground truth").

    python lab/bench/icp_settings.py                  # 60 s per scene, a few minutes
    python lab/bench/icp_settings.py --duration 20    # quicker
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from typing import Any, Sequence

# One setting at a time, from the defaults: (label, IcpConfig changes).
FOREST_ROWS: tuple[tuple[str, dict[str, Any]], ...] = (
    ('defaults', {}),
    ('before the data-driven voxel: range 60 m, voxel 0.6 m, convergence 1e-4',
     {'max_range_m': 60.0, 'voxel_size_m': 0.6, 'convergence': 1e-4}),
    ('voxel 0.6 m', {'voxel_size_m': 0.6}),
    ('voxel 1.0 m', {'voxel_size_m': 1.0}),
    ('voxel 2.0 m', {'voxel_size_m': 2.0}),
    ('max range 60 m', {'max_range_m': 60.0}),
    ('max range 40 m', {'max_range_m': 40.0}),
    ('points per voxel 10', {'max_points_per_voxel': 10}),
    ('points per voxel 5', {'max_points_per_voxel': 5}),
    ('convergence 1e-4', {'convergence': 1e-4}),
    ('convergence 1e-2', {'convergence': 1e-2}),
    ('at most 10 iterations', {'max_iterations': 10}),
    ('every 2nd scan', {'stride': 2}),
    ('every 3rd scan', {'stride': 3}),
)
COURTYARD_ROWS: tuple[tuple[str, dict[str, Any]], ...] = (
    ('defaults', {}),
    ('before the data-driven voxel: range 60 m, voxel 0.6 m, convergence 1e-4',
     {'max_range_m': 60.0, 'voxel_size_m': 0.6, 'convergence': 1e-4}),
    ('voxel 1.0 m', {'voxel_size_m': 1.0}),
    ('voxel 1.5 m', {'voxel_size_m': 1.5}),
    ('convergence 1e-4', {'convergence': 1e-4}),
    ('every 2nd scan', {'stride': 2}),
)


def _scene(name: str, duration_s: float) -> Any:
    from gt_bench import outdoor_config

    from skidkin_ros.sim import LidarConfig, SimConfig, simulate

    if name == 'forest':
        return simulate(outdoor_config(duration_s, seed=21))
    lidar = LidarConfig(azimuth_resolution_deg=0.5, mount_xyz_m=(0.3, 0.1, 0.5),
                        mount_yaw_rad=0.4)
    return simulate(SimConfig(duration_s=duration_s, seed=22, lidar=lidar,
                              internal_rate_hz=200.0))


def measure(sim: Any, scans: Sequence[Any], changes: dict[str, Any]) -> dict[str, Any]:
    """Register the scans with one setting changed; return CPU ms per scan and the errors."""
    from skidkin_ros.adapters.lidar_gt import guarded_truth, IcpConfig, register_frames
    from skidkin_ros.core.drive import PoseTrack
    from skidkin_ros.sim.accuracy import increment_errors

    config = dataclasses.replace(IcpConfig(), **changes)
    tic = time.process_time()
    registration = register_frames(scans, config)
    cpu = (time.process_time() - tic) / len(scans)
    truth = guarded_truth(registration, sim.config.lidar.extrinsic(), config)
    track = PoseTrack(truth.track.t_ns, truth.track.x, truth.track.y, truth.track.yaw,
                      truth.track.valid)  # score only what the guard kept
    one = increment_errors(track, sim.pose_at, horizon_s=1.0)
    two = increment_errors(track, sim.pose_at, horizon_m=2.0)
    return {'cpu_ms': 1e3 * cpu, 'voxel_m': registration.voxel_size_m,
            'pos_1s_m': one.median_position_m, 'yaw_1s_rad': one.median_yaw_rad,
            'pos_2m_m': two.median_position_m, 'yaw_2m_rad': two.median_yaw_rad}


def run(duration_s: float, scenes: Sequence[str] = ('forest', 'courtyard')) -> dict[str, Any]:
    """Return the table: per scene, one row per setting."""
    out: dict[str, Any] = {'duration_s': duration_s, 'scenes': {}}
    for name in scenes:
        sim = _scene(name, duration_s)
        scans = list(sim.scans())
        rows = []
        for label, changes in (FOREST_ROWS if name == 'forest' else COURTYARD_ROWS):
            print(f'  icp settings: {name}, {label}', flush=True)
            row = {'setting': label}
            row.update(measure(sim, scans, changes))
            rows.append(row)
        out['scenes'][name] = {'scans': len(scans),
                               'points_per_scan': sum(len(s) for s in scans) / len(scans),
                               'rows': rows}
    return out


def markdown(table: dict[str, Any]) -> list[str]:
    """Return the table as Markdown lines."""
    lines = []
    for name, scene in table['scenes'].items():
        lines += [f'**{name}** ({scene["scans"]} scans of {scene["points_per_scan"]:.0f} points, '
                  f'{table["duration_s"]:g} s):', '',
                  '| setting | voxel m | CPU ms/scan | 1 s: cm | 1 s: mrad | 2 m: cm | '
                  '2 m: mrad |', '|---|---|---|---|---|---|---|']
        for r in scene['rows']:
            lines.append(f'| {r["setting"]} | {r["voxel_m"]:.2f} | {r["cpu_ms"]:.1f} | '
                         f'{100 * r["pos_1s_m"]:.2f} | {1e3 * r["yaw_1s_rad"]:.2f} | '
                         f'{100 * r["pos_2m_m"]:.2f} | {1e3 * r["yaw_2m_rad"]:.2f} |')
        lines.append('')
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    """Print the table (Markdown) and write it as JSON with --json."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--duration', type=float, default=60.0, help='seconds per scene')
    parser.add_argument('--json', help='also write the table here')
    args = parser.parse_args(argv)
    table = run(args.duration)
    print('\n'.join(markdown(table)))
    if args.json:
        with open(args.json, 'w', encoding='utf-8') as stream:
            json.dump(table, stream, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
