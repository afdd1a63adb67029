"""Lidar pipeline benchmark: bag reading, kiss-icp and fitting per frame; peak memory.

For each recording length a simulated drive with lidar is written to a rosbag2 (not timed), then:

* bag reading: wheel speeds, the base_link -> lidar extrinsic and every lidar frame read into
  memory with :meth:`BagRecording.iter_lidar`;
* ICP: :func:`lidar_ground_truth` on the frames already in memory (kiss-icp in this process,
  one thread, no chunks);
* fitting: the five models fitted on segments cut from the ICP ground truth;
* peak memory: a fresh interpreter runs the streaming pipeline the CLI uses
  (:func:`load_source` with ICP ground truth: frames are read as kiss-icp consumes them) and
  reports its peak resident set size, and the peak after the imports alone.

Real-time factor = recording duration / (reading + ICP + fitting time).
Run as ``python lab/bench/lidar_bench.py memory BAG`` for the memory probe alone (JSON on stdout).
"""

from __future__ import annotations

import json
from pathlib import Path
import resource
import subprocess
import sys
import time
from typing import Any, Sequence

MEMORY_MARK = 'BENCH_MEMORY '


def _bag_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in Path(path).rglob('*') if f.is_file())


def write_recording(folder: Path, duration_s: float, azimuth_deg: float, seed: int) -> Path:
    """Simulate a drive with lidar and write it as a bag; return the bag path."""
    from skidkin_ros.adapters.sim_writer import write_bag
    from skidkin_ros.sim import LidarConfig, SimConfig, simulate

    config = SimConfig(duration_s=duration_s, seed=seed, internal_rate_hz=200.0,
                       lidar=LidarConfig(azimuth_resolution_deg=azimuth_deg))
    bag, _ = write_bag(simulate(config), folder / f'lidar_{int(duration_s)}s')
    return bag


def time_stages(bag: Path, horizon_m: float) -> dict[str, Any]:
    """Time reading, ICP on in-memory frames and fitting on one bag."""
    from skidkin_ros.adapters.bag_reader import open_recording
    from skidkin_ros.adapters.lidar_gt import IcpConfig, lidar_ground_truth
    from skidkin_ros.core.drive import Drive
    from skidkin_ros.core.calibration.fitting import fit_models
    from skidkin_ros.core.calibration.segments import cut_segments, SegmentOptions
    from skidkin_ros.errors import SkidkinError
    from skidkin_ros.sim import SimConfig

    tic = time.perf_counter()
    with open_recording(bag) as rec:
        wheels = rec.read_wheels()
        frames = list(rec.iter_lidar())
        extrinsic = rec.read_extrinsic('base_link', frames[0].frame_id)
    read_s = time.perf_counter() - tic
    points = sum(len(frame.xyz) for frame in frames)
    tic = time.perf_counter()
    truth = lidar_ground_truth(frames, extrinsic, IcpConfig())
    icp_s = time.perf_counter() - tic
    duration_s = (frames[-1].end_ns - frames[0].stamp_ns) / 1e9
    del frames
    tic = time.perf_counter()
    fit_error = None
    segments = 0
    try:
        cut = cut_segments([Drive(bag.name, wheels, truth.track, None, {})],
                           SegmentOptions(horizon_m=horizon_m))
        segments = len(cut)
        fit_models(SimConfig().geometry, cut)
    except SkidkinError as err:
        fit_error = f'{type(err).__name__}: {err}'
    fit_s = time.perf_counter() - tic
    n_frames = len(truth.frame_status)
    total_s = read_s + icp_s + fit_s
    return {
        'frames': n_frames, 'points_per_frame': points / max(n_frames, 1),
        'duration_s': duration_s, 'bag_mb': _bag_bytes(bag) / 1e6,
        'read_s': read_s, 'icp_s': icp_s, 'fit_s': fit_s, 'segments': segments,
        'fit_error': fit_error, 'icp_ok_frames': int(truth.counts.get('ok', 0)),
        'read_ms_per_frame': 1e3 * read_s / n_frames, 'icp_ms_per_frame': 1e3 * icp_s / n_frames,
        'total_ms_per_frame': 1e3 * total_s / n_frames,
        'real_time_factor': duration_s / total_s,
        'icp_real_time_factor': duration_s / icp_s,
    }


def peak_memory(bag: Path) -> dict[str, Any]:
    """Run the streaming pipeline on a bag in a fresh interpreter; return its peak RSS (MB)."""
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), 'memory', str(bag)],
                          capture_output=True, text=True, timeout=600)
    for line in proc.stdout.splitlines():
        if line.startswith(MEMORY_MARK):
            return json.loads(line[len(MEMORY_MARK):])
    tail = ' | '.join((proc.stderr or '').strip().splitlines()[-3:])
    return {'error': f'memory probe exited with {proc.returncode}: {tail}'}


def peak_rss_mb() -> float:
    """Return this process's peak resident set size (MB) since it started.

    /proc/self/status VmHWM, which starts afresh at exec; ru_maxrss (the fallback) keeps the
    high-water mark of the parent at fork time, which would hide the probe's own peak.
    """
    try:
        with open('/proc/self/status', encoding='ascii') as stream:
            for line in stream:
                if line.startswith('VmHWM:'):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _memory_probe(bag: Path) -> dict[str, Any]:
    from skidkin_ros.adapters.sources import load_source, SourceOptions
    import kiss_icp.kiss_icp  # noqa: F401 - count the imports in the baseline

    baseline_mb = peak_rss_mb()
    tic = time.perf_counter()
    options = SourceOptions(ground_truth='icp', min_overlap_s=1.0)
    loaded = load_source(bag, options)
    seconds = time.perf_counter() - tic
    peak_mb = peak_rss_mb()
    truth = loaded.drives[0].truth
    return {'after_imports_mb': baseline_mb, 'peak_mb': peak_mb,
            'pipeline_mb': peak_mb - baseline_mb, 'seconds': seconds, 'poses': len(truth)}


def run(folder: Path, durations_s: Sequence[float], azimuth_deg: float,
        horizon_m: float) -> dict[str, Any]:
    """Benchmark every recording length on the courtyard, the longest on the outdoor scene."""
    from gt_bench import write_outdoor

    rows = []
    for i, duration_s in enumerate(durations_s):
        bag = write_recording(folder, duration_s, azimuth_deg, seed=40 + i)
        row = time_stages(bag, horizon_m)
        row['memory'] = peak_memory(bag)
        row['scene'] = f'courtyard, {azimuth_deg:g} deg'
        rows.append(row)
    bag, _ = write_outdoor(folder, max(durations_s), seed=49)
    row = time_stages(bag, horizon_m)
    row['memory'] = peak_memory(bag)
    row['scene'] = 'outdoor (400 trees), VLP-16-like, 1 deg'
    rows.append(row)
    return {'rows': rows, 'azimuth_resolution_deg': azimuth_deg, 'horizon_m': horizon_m}


def _main(argv: Sequence[str]) -> int:
    if len(argv) != 2 or argv[0] != 'memory':
        print('usage: lidar_bench.py memory BAG', file=sys.stderr)
        return 2
    print(MEMORY_MARK + json.dumps(_memory_probe(Path(argv[1]))))
    return 0


if __name__ == '__main__':
    sys.exit(_main(sys.argv[1:]))
