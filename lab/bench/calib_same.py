"""Calibrate with exact and with finite-difference Jacobians; compare what is written.

``skidkin calibrate``'s model fits use the exact (forward-mode) Jacobian of the segment errors
(:func:`~skidkin_ros.core.calibration.fitting.segment_errors_jacobian`); scipy's finite
differences remain as ``fitting.EXACT_JACOBIAN = False``. This runs
:func:`~skidkin_ros.core.calibration.pipeline.calibrate_interval` both ways in one process and
reports: whether the written parameters file (its values), the printed table and the warnings
are identical; the largest difference of every fitted parameter in its standard errors; and
the largest relative difference of any written value.

    PYTHONPATH=. python lab/bench/calib_same.py husky      # the Husky table, calib_step split
    PYTHONPATH=. python lab/bench/calib_same.py 2          # 2 km of the bench's drives
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
import sys
import time
from typing import Any

ROOT = Path(__file__).resolve().parents[2]


def _inputs(case: str):
    from skidkin_ros.core.calibration.pipeline import CalibrationOptions
    from skidkin_ros.core.kinematics.specs import Geometry
    if case == 'husky':
        from skidkin_ros.adapters.table import read_table
        from skidkin_ros.core.calibration.holdout import split_holdout
        drives = read_table(ROOT / 'data' / 'husky' / 'drive_husky_windows.csv')
        train, evaluate = split_holdout(drives, every=2, key='calib_step')
        return (train, evaluate, Geometry(0.1651, 0.555),
                CalibrationOptions(holdout_key='calib_step'))
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from calib_bench import first_km, simulate_drives
    from skidkin_ros.sim import SimConfig
    km = float(case)
    drives = first_km(simulate_drives(km, 600.0), km)
    return (drives, None, SimConfig().geometry,
            CalibrationOptions(holdout_mode='time', holdout_block_s=60.0))


def _calibrate(inputs, exact: bool) -> dict[str, Any]:
    from skidkin_ros.cli.common import print_calibration
    from skidkin_ros.core.calibration import fitting
    from skidkin_ros.core.calibration.pipeline import calibrate_interval
    from skidkin_ros.core.calibration.results import result_to_parameters
    from skidkin_ros.core.parallel import one_blas_thread
    train, evaluate, geometry, options = inputs
    fitting.EXACT_JACOBIAN = exact
    with one_blas_thread():
        tic = time.perf_counter()
        result = calibrate_interval(train, evaluate, geometry, options)
        seconds = time.perf_counter() - tic
    table = io.StringIO()
    with contextlib.redirect_stdout(table):
        print_calibration(result)
    warnings = [w for f in result.fits.values() for w in f.warnings]
    return {'result': result, 'table': table.getvalue(), 'warnings': warnings,
            'written': result_to_parameters(result, {}, allow_invalid=False),
            'seconds': seconds}


def _numbers(flat: dict[str, Any]) -> dict[str, float]:
    out = {}
    for key, value in flat.items():
        if isinstance(value, bool):
            continue
        if isinstance(value, (int, float)):
            out[key] = float(value)
        elif isinstance(value, (list, tuple)) and all(isinstance(v, (int, float)) for v in value):
            out.update({f'{key}[{i}]': float(v) for i, v in enumerate(value)})
    return out


def compare(case: str) -> dict[str, Any]:
    """Calibrate ``case`` both ways (module docstring); return the comparison."""
    inputs = _inputs(case)
    fd, exact = _calibrate(inputs, False), _calibrate(inputs, True)
    gaps_se = {}
    for name, fit in fd['result'].fits.items():
        other = exact['result'].fits[name]
        for key, value in fit.values.items():
            se = fit.std_errors[key]
            gaps_se[f'{name}.{key}'] = abs(other.values[key] - value) / se if se > 0 else 0.0
    a, b = _numbers(fd['written']), _numbers(exact['written'])
    rel = {k: abs(b[k] - v) / max(abs(v), 1e-300) for k, v in a.items() if k in b and v != b[k]}
    table_lines = [(x, y) for x, y in zip(fd['table'].splitlines(), exact['table'].splitlines())
                   if x != y]
    return {'case': case, 'best': [fd['result'].best, exact['result'].best],
            'seconds_fd_exact': [round(fd['seconds'], 2), round(exact['seconds'], 2)],
            'written_identical': fd['written'] == exact['written'],
            'written_keys_same': sorted(fd['written']) == sorted(exact['written']),
            'written_max_rel_diff': max(rel.values(), default=0.0),
            'written_differing': [(k, a[k], b[k]) for k in sorted(rel, key=rel.get,
                                                                  reverse=True)[:8]],
            'written_max_rel_diff_above_1e-10': max((r for k, r in rel.items()
                                                     if abs(a[k]) > 1e-10), default=0.0),
            'table_identical': fd['table'] == exact['table'],
            'table_lines_differing': table_lines[:6],
            'warnings_identical': fd['warnings'] == exact['warnings'],
            'max_gap_in_se': max(gaps_se.values(), default=0.0),
            'worst_parameter': max(gaps_se, key=gaps_se.get) if gaps_se else None}


if __name__ == '__main__':
    print(json.dumps(compare(sys.argv[1] if len(sys.argv) > 1 else 'husky'), indent=1))
