"""Calibration time, today's code path beside the earlier one, in the same run.

``skidkin calibrate`` runs :func:`~skidkin_ros.core.calibration.pipeline.calibrate_interval`.
The earlier path (``interval_search='full'``, ``jobs=1``) ran the whole recipe, gyro included,
under every sample-interval convention, one model after the other; today's refits only the
winning model under the other conventions, calibrates the gyro once, and calibrates the models
in parallel (forked workers, one per usable CPU). Both give the same parameters file: the
bench checks the written model and its values agree.

The two are timed alternately (earlier, today, earlier, today...) on the same drives, so the
ratio holds under a machine's changing load; the median of each is reported.
"""

from __future__ import annotations

from dataclasses import replace
import statistics
import time
from typing import Any, Sequence

from skidkin_ros.core.calibration.pipeline import calibrate_interval, CalibrationOptions
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.parallel import usable_cpus


def _timed(drives: Sequence[Drive], geometry, options: CalibrationOptions,
           search: str) -> tuple[float, Any]:
    tic = time.perf_counter()
    result = calibrate_interval(list(drives), None, geometry, options, interval_search=search)
    return time.perf_counter() - tic, result


def before_after(drives: Sequence[Drive], geometry, options: CalibrationOptions,
                 rounds: int = 1) -> dict[str, Any]:
    """Time the earlier and today's calibration of the same drives, alternately."""
    earlier_opts = replace(options, jobs=1)
    times: dict[str, list[float]] = {'earlier_s': [], 'today_s': []}
    results = {}
    for _ in range(rounds):
        seconds, results['earlier'] = _timed(drives, geometry, earlier_opts, 'full')
        times['earlier_s'].append(seconds)
        seconds, results['today'] = _timed(drives, geometry, options, 'fits')
        times['today_s'].append(seconds)
    earlier, today = results['earlier'], results['today']
    same = (earlier.best == today.best and earlier.options.interval == today.options.interval
            and earlier.fits[earlier.best].values == today.fits[today.best].values)
    out = {key: statistics.median(value) for key, value in times.items()}
    out.update(ratio=out['earlier_s'] / out['today_s'], rounds=rounds, cpus=usable_cpus(),
               same_result=same, best=today.best, interval=today.options.interval,
               fit_s_today=sum(f.seconds for f in today.fits.values()))
    return out
