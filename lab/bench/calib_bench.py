"""Calibration benchmark: the whole calibration recipe against the distance driven.

Drives are simulated once (no lidar: truth straight from the simulator), then the first drives
totalling at least 0.5, 1, 2 and 4 km are calibrated with the default options (all five
models, hold-out of 1 time block in 3). Cost should grow linearly: time per km is reported
for each size and the ratio of the largest to the smallest. The simulation itself is not timed.
"""

from __future__ import annotations

from dataclasses import replace
import time
from typing import Any, Sequence

import calib_speed
from skidkin_ros.core.calibration.pipeline import calibrate, CalibrationOptions
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.parallel import usable_cpus
from skidkin_ros.sim import SimConfig, simulate
from threadpoolctl import threadpool_limits


def simulate_drives(total_km: float, drive_s: float, seed: int = 100) -> list[Drive]:
    """Simulate drives of drive_s seconds until they total at least total_km of true path."""
    drives: list[Drive] = []
    travelled_m = 0.0
    index = 0
    while travelled_m < total_km * 1000.0:
        # 200 Hz truth grid: plenty for 20 Hz encoders, and five times cheaper to simulate.
        sim = simulate(SimConfig(duration_s=drive_s, seed=seed + index, internal_rate_hz=200.0))
        drive = sim.drive(f'bench_{index:03d}')
        drives.append(drive)
        travelled_m += float(drive.truth.path_length()[-1])
        index += 1
    return drives


def first_km(drives: Sequence[Drive], km: float) -> list[Drive]:
    """Return the first drives whose true paths total at least km."""
    chosen: list[Drive] = []
    travelled_m = 0.0
    for drive in drives:
        if travelled_m >= km * 1000.0:
            break
        chosen.append(drive)
        travelled_m += float(drive.truth.path_length()[-1])
    return chosen


def blas_threads(drives: Sequence[Drive], geometry, options: CalibrationOptions
                 ) -> dict[str, Any]:
    """Time one calibration with BLAS on every usable CPU, then on one (core.parallel)."""
    out: dict[str, Any] = {'threads': usable_cpus()}
    for key, limit in (('all_threads_s', usable_cpus()), ('one_thread_s', 1)):
        with threadpool_limits(limits=limit, user_api='blas'):
            tic = time.perf_counter()
            calibrate(list(drives), None, geometry, options)
            out[key] = time.perf_counter() - tic
    out['ratio'] = out['all_threads_s'] / out['one_thread_s']
    return out


def run(sizes_km: Sequence[float], drive_s: float, holdout_block_s: float = 60.0,
        n_starts: int | None = None) -> dict[str, Any]:
    """Calibrate on growing prefixes of one set of simulated drives; return the rows.

    The hold-out is always by time blocks (holdout_block_s) so every size is split alike;
    n_starts (multi-start fits) defaults to the calibration default.
    """
    tic = time.perf_counter()
    drives = simulate_drives(max(sizes_km), drive_s)
    simulate_s = time.perf_counter() - tic
    geometry = SimConfig().geometry
    options = CalibrationOptions(holdout_mode='time', holdout_block_s=holdout_block_s)
    if n_starts is not None:
        options = replace(options, n_starts=n_starts)
    rows = []
    for km in sizes_km:
        chosen = first_km(drives, km)
        path_km = sum(float(d.truth.path_length()[-1]) for d in chosen) / 1000.0
        samples = sum(len(d.wheels) for d in chosen)
        tic = time.perf_counter()
        result = calibrate(chosen, None, geometry, options)
        total_s = time.perf_counter() - tic
        fit_s = sum(fit.seconds for fit in result.fits.values())
        rows.append({
            'target_km': km, 'km': path_km, 'drives': len(chosen), 'wheel_samples': samples,
            'train_segments': len(result.train_segments),
            'eval_segments': len(result.eval_segments),
            'calibrate_s': total_s, 'fit_s': fit_s, 'other_s': total_s - fit_s,
            's_per_km': total_s / path_km,
            'fit_s_by_model': {name: fit.seconds for name, fit in result.fits.items()},
            'best': result.best,
        })
    per_km = [row['s_per_km'] for row in rows]
    blas = blas_threads(first_km(drives, min(sizes_km)), geometry, options)
    # as skidkin calibrate runs it: today's path beside the earlier one (calib_speed.py)
    speed_km = 2.0 if 2.0 in sizes_km else max(sizes_km)
    speed_options = {'holdout_mode': 'time', 'holdout_block_s': holdout_block_s,
                     **({'n_starts': n_starts} if n_starts is not None else {})}
    speed = {'km': speed_km, **calib_speed.before_after(first_km(drives, speed_km),
                                                        speed_options)}
    return {
        'blas': blas, 'before_after': speed,
        'rows': rows, 'simulate_s': simulate_s, 'drive_s': drive_s,
        'holdout_block_s': holdout_block_s, 'n_starts': options.n_starts,
        'per_km_ratio_largest_smallest': per_km[-1] / per_km[0] if per_km else float('nan'),
        'time_at_2km_s': next((r['calibrate_s'] for r in rows if r['target_km'] == 2.0),
                              None),
    }
