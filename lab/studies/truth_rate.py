"""Does the calibrator need the lidar truth at the scan rate? Calibrate on 10 Hz and 5 Hz truth.

A simulated drive's truth is sampled at the lidar's 10 Hz (every scan registered) and at 5 Hz
(one scan in two, ``skidkin groundtruth --stride 2``); the same wheels and IMU; the calibrator
fits every model on both, and the parameters are compared with their standard errors.

    python -m lab.studies.truth_rate --seeds 5 11 --duration 300
"""

from __future__ import annotations

import argparse
from dataclasses import replace
import sys
from typing import Sequence

import numpy as np

from skidkin_ros.core.calibration.pipeline import calibrate, CalibrationOptions
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.sim.simulate import SimConfig, simulate


def truth_at_rate(sim, rate_hz: float) -> PoseTrack:
    """Return the true track sampled at ``rate_hz`` from the drive's start."""
    step = int(round(1e9 / rate_hz))
    t_ns = np.arange(sim.start_ns, sim.end_ns + 1, step, dtype=np.int64)
    return sim.truth_at(t_ns)


def compare(seed: int, duration_s: float, models: Sequence[str]) -> list[dict]:
    sim = simulate(SimConfig(duration_s=duration_s, seed=seed))
    geometry = sim.config.geometry
    drive = sim.drive('sim')
    options = CalibrationOptions(models=tuple(models))
    rows = []
    results = {}
    for rate in (10.0, 5.0):
        d = replace(drive, truth=truth_at_rate(sim, rate), name=f'sim{rate:g}')
        results[rate] = calibrate([d], None, geometry, options)
    full, half = results[10.0], results[5.0]
    for model in models:
        a, b = full.fits[model], half.fits[model]
        for name, value in a.values.items():
            se = max(a.std_errors.get(name, np.nan), 1e-12)
            rows.append({'seed': seed, 'model': model, 'param': name, 'v10': value,
                         'v5': b.values[name], 'se10': se, 'se5': b.std_errors.get(name),
                         'diff_in_se': abs(b.values[name] - value) / se})
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[5, 11])
    parser.add_argument('--duration', type=float, default=300.0)
    parser.add_argument('--models', nargs='+', default=['edd_symmetric', 'edd_asymmetric'])
    args = parser.parse_args(argv)
    print('| seed | model | parameter | 10 Hz truth | 5 Hz truth | std error (10 Hz) | '
          '|diff| / std error |')
    print('|---|---|---|---|---|---|---|')
    worst = 0.0
    for seed in args.seeds:
        for r in compare(seed, args.duration, args.models):
            worst = max(worst, r['diff_in_se'])
            print(f"| {r['seed']} | {r['model']} | {r['param']} | {r['v10']:.5f} | "
                  f"{r['v5']:.5f} | {r['se10']:.5f} | {r['diff_in_se']:.2f} |")
    print(f'largest difference: {worst:.2f} standard errors')
    return 0


if __name__ == '__main__':
    sys.exit(main())
