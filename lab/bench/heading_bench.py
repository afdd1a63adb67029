"""Heading at window ends on the Husky: the calibrated model against a plain window-end fit.

A calibrator with unit weights traded heading away. This bench keeps the comparison in every
run, on the real Husky table (DRIVE windows of 2 s, split by ``calib_step``: even steps train,
odd steps evaluate, as in docs/results.md):

* **calibrated**: ``calibrate()`` with the default options, each trained model as written;
* **plain window-end fit** (the reference): the same model fitted on the same training
  windows, one segment per 2 s window (first to last pose), x, y and yaw residuals with unit
  weights, no trimming (``fit_model`` with Sigma = identity, ``trim`` off).

Both are scored on the held-out windows: median |heading error| and median |position error|
at the window ends. The check (a bench check, not a timed test): the calibrated best model is
not worse in heading than its reference, and its position error at the window ends is within
5 % of the reference's.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
import time
from typing import Any

from skidkin_ros.adapters.table import read_table
from skidkin_ros.core.calibration.evaluation import window_end_errors
from skidkin_ros.core.calibration.fitting import fit_model, FitOptions
from skidkin_ros.core.calibration.holdout import split_holdout
from skidkin_ros.core.calibration.pipeline import calibrate, CalibrationOptions
from skidkin_ros.core.calibration.segments import cut_segments
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry

HUSKY_CSV = Path(__file__).resolve().parents[2] / 'data' / 'husky' / 'drive_husky_windows.csv'
HUSKY = Geometry(0.1651, 0.555)
TRANSLATION_TOLERANCE = 0.05


def run(csv_path: Path = HUSKY_CSV) -> dict[str, Any]:
    """Calibrate the Husky split and fit the plain reference; return the rows and the verdict."""
    if not csv_path.is_file():
        return {'available': False, 'reason': f'{csv_path} not found', 'rows': []}
    tic = time.perf_counter()
    drives = read_table(csv_path)
    train, evaluate = split_holdout(drives, every=2, key='calib_step')
    options = CalibrationOptions(holdout_key='calib_step')
    result = calibrate(train, evaluate, HUSKY, options)
    window_options = replace(options.eval_segments(), horizon_s=options.window_s)
    train_windows = cut_segments(train, window_options)
    eval_windows = cut_segments(evaluate, window_options)
    plain_options = FitOptions(trim=False)
    rows = []
    for name, fit in result.fits.items():
        if not get_model(name).params:
            continue
        plain = fit_model(name, HUSKY, train_windows, plain_options)
        calibrated_end = window_end_errors(name, fit.values, HUSKY, eval_windows)
        plain_end = window_end_errors(name, plain.values, HUSKY, eval_windows)
        rows.append({
            'model': name, 'best': name == result.best, 'valid': fit.valid,
            'calibrated_yaw_rad': calibrated_end.yaw_rad,
            'calibrated_position_m': calibrated_end.position_m,
            'plain_yaw_rad': plain_end.yaw_rad, 'plain_position_m': plain_end.position_m,
            'calibrated_values': dict(fit.values), 'plain_values': dict(plain.values),
        })
    best = next(r for r in rows if r['best']) if any(r['best'] for r in rows) else None
    verdict = {}
    if best is not None:
        verdict = {
            'model': best['model'],
            'heading_not_worse': best['calibrated_yaw_rad'] <= best['plain_yaw_rad'],
            'translation_ratio': best['calibrated_position_m'] / best['plain_position_m'],
        }
        verdict['translation_within'] = (verdict['translation_ratio']
                                         <= 1.0 + TRANSLATION_TOLERANCE)
    return {'available': True, 'rows': rows, 'verdict': verdict, 'best': result.best,
            'train_windows': len(train_windows), 'eval_windows': len(eval_windows),
            'weighting': options.weighting, 'selection': result.selection_rule,
            'seconds': time.perf_counter() - tic}
