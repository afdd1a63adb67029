"""Diagnosis benchmark: time of ``diagnose`` against the distance driven, on one and all CPUs.

Drives come from the same simulator as the calibration benchmark (true model edd_asymmetric, so
a default edd_symmetric leaves residuals to explain); the base model is edd_symmetric at its
defaults. A diagnosis that fails is reported ('available': False, with the reason) instead of
stopping the other benchmarks.
"""

from __future__ import annotations

import time
from typing import Any, Sequence

from calib_bench import first_km, simulate_drives
from skidkin_ros.core.calibration.diagnosis import diagnose, DiagnosisOptions
from skidkin_ros.core.parallel import usable_cpus
from skidkin_ros.sim import SimConfig


def _outcome(result: Any) -> tuple:
    """Return what a diagnosis found, without its timings."""
    scores = [(c.round_no, c.name, c.relative_gain, c.p_value, c.accepted, c.values, c.terms)
              for c in result.candidates]
    return result.final, scores, [step.stats_t for step in result.steps]


def run(sizes_km: Sequence[float], drive_s: float, holdout_block_s: float = 60.0
        ) -> dict[str, Any]:
    """Diagnose growing prefixes of one set of simulated drives, serially and on every CPU.

    Returns the rows: per size, the time with one process and with ``jobs`` (every usable CPU),
    their ratio, and whether both runs found the same result (they must).
    """
    drives = simulate_drives(max(sizes_km), drive_s, seed=300)
    geometry = SimConfig().geometry
    jobs = usable_cpus()
    rows = []
    for km in sizes_km:
        chosen = first_km(drives, km)
        path_km = sum(float(d.truth.path_length()[-1]) for d in chosen) / 1000.0
        options = DiagnosisOptions(holdout_mode='time', holdout_block_s=holdout_block_s)
        timed = {}
        for count in (1, jobs):
            if count in timed:
                continue
            tic = time.perf_counter()
            try:
                result = diagnose(chosen, None, geometry, {'edd_symmetric': {}},
                                  'edd_symmetric', options, jobs=count)
            except Exception as err:  # noqa: B902 - report, do not crash the other benchmarks
                return {'available': False, 'rows': rows,
                        'reason': f'diagnose failed: {type(err).__name__}: {err}'}
            timed[count] = (time.perf_counter() - tic, result)
        serial_s, serial = timed[1]
        parallel_s, parallel = timed[jobs]
        rows.append({'target_km': km, 'km': path_km, 'drives': len(chosen), 'jobs': jobs,
                     'diagnose_s': parallel_s, 's_per_km': parallel_s / path_km,
                     'serial_s': serial_s, 'serial_s_per_km': serial_s / path_km,
                     'speedup': serial_s / parallel_s,
                     'same_result': _outcome(serial) == _outcome(parallel),
                     'accepted': list(parallel.extensions)})
    return {'available': True, 'rows': rows}
