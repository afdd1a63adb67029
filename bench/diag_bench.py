"""Diagnosis benchmark: time of ``diagnose`` against the distance driven.

The diagnosis feature (skidkin_ros.core.diagnosis) is optional here: when it cannot be imported
the result says so ('not available') instead of inventing numbers. Drives come from the same
simulator as the calibration benchmark (true model edd_asymmetric, so a default edd_symmetric
leaves residuals to explain); the base model is edd_symmetric at its defaults.
"""

from __future__ import annotations

import time
from typing import Any, Sequence

from calib_bench import first_km, simulate_drives
from skidkin_ros.sim import SimConfig


def run(sizes_km: Sequence[float], drive_s: float, holdout_block_s: float = 60.0
        ) -> dict[str, Any]:
    """Diagnose growing prefixes of one set of simulated drives; return the rows."""
    try:
        from skidkin_ros.core.diagnosis import diagnose, DiagnosisOptions
    except ImportError as err:
        return {'available': False, 'reason': f'not available yet ({err})', 'rows': []}
    drives = simulate_drives(max(sizes_km), drive_s, seed=300)
    geometry = SimConfig().geometry
    rows = []
    for km in sizes_km:
        chosen = first_km(drives, km)
        path_km = sum(float(d.truth.path_length()[-1]) for d in chosen) / 1000.0
        tic = time.perf_counter()
        try:
            options = DiagnosisOptions(holdout_mode='time', holdout_block_s=holdout_block_s)
            result = diagnose(chosen, None, geometry, {'edd_symmetric': {}}, 'edd_symmetric',
                              options)
        except Exception as err:  # noqa: B902 - a feature in progress: report, do not crash
            return {'available': False, 'rows': rows,
                    'reason': f'diagnose failed: {type(err).__name__}: {err}'}
        seconds = time.perf_counter() - tic
        accepted = getattr(result, 'extensions', None)
        rows.append({'target_km': km, 'km': path_km, 'drives': len(chosen),
                     'diagnose_s': seconds, 's_per_km': seconds / path_km,
                     'accepted': list(accepted) if accepted is not None else None})
    return {'available': True, 'rows': rows}
