"""Held-out window ends on windowed data: the written model beside its plain window-end fit.

Two data sets with the traits of the DRIVE tables (independent 2 s windows, many spins,
transients), each split by ``calib_step`` (even steps train, odd steps evaluate):

* **husky**: the real Husky table of ``data/husky``;
* **warthog_sim**: a Warthog-like robot simulated by
  :func:`skidkin_ros.sim.windows.simulate_windows` (r = 0.3 m, b = 1.2 m, asymmetric treads,
  acceleration slip, a first-order body lag and a
  yaw-rate loss at high wheel-speed ratios: transients and effects no kinematic model has).

For each training-segment scheme (``rotation``, ``paper``, ``time``) the calibration is run as
``skidkin calibrate`` runs it (``calibrate_interval``, default options otherwise) and its written
model is scored beside the plain fit of the same model (one segment per training window, unit
weights, no trimming), both at the held-out window ends: median |position error| (m) and median
|heading error| (rad). Goal: both ratios <= 1.0, one of them <= 0.9.

Run alone::

    python -m lab.bench.segments_bench            # both data sets, three schemes
"""

from __future__ import annotations

import argparse
from dataclasses import replace
import json
from pathlib import Path
import sys
import time
from typing import Any, Sequence

from skidkin_ros.adapters.table import read_table
from skidkin_ros.core.calibration.holdout import split_holdout
from skidkin_ros.core.calibration.pipeline import (calibrate_interval, CalibrationOptions,
                                                   TRAIN_SEGMENTS)
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.parallel import one_blas_thread
from skidkin_ros.sim.windows import simulate_windows, WARTHOG_LIKE

HUSKY_CSV = Path(__file__).resolve().parents[2] / 'data' / 'husky' / 'drive_husky_windows.csv'
HUSKY = Geometry(0.1651, 0.555)
DOMINANCE_GAIN = 0.9


def datasets(sim_steps: int = 150) -> dict[str, tuple[list, Geometry]]:
    """Return {name: (drives, geometry)}: the Husky table (when present) and the simulation."""
    out = {}
    if HUSKY_CSV.is_file():
        out['husky'] = (read_table(HUSKY_CSV), HUSKY)
    config = replace(WARTHOG_LIKE, steps=sim_steps)
    out['warthog_sim'] = (simulate_windows(config),
                          Geometry(config.wheel_radius, config.track_width))
    return out


def score(drives: Sequence, geometry: Geometry, segments: str) -> dict[str, Any]:
    """Calibrate as the CLI does with one segment scheme; return the written and plain numbers."""
    train, evaluate = split_holdout(drives, every=2, key='calib_step')
    options = CalibrationOptions(holdout_key='calib_step', segments=segments)
    tic = time.perf_counter()
    result = calibrate_interval(train, evaluate, geometry, options)
    seconds = time.perf_counter() - tic
    written = result.window_end[result.best]
    plain = result.plain_window_end
    row = {'segments': segments, 'model': result.best, 'interval': result.options.interval,
           'written_position_m': written.position_m, 'written_yaw_rad': written.yaw_rad,
           'windows': written.windows, 'seconds': seconds,
           'nees': {m: [round(c.mean_nees, 2) for c in nf.consistency.horizons]
                    for m, nf in result.noise.items() if m == result.best},
           'nees_verdicts': [c.verdict for c in result.noise[result.best].consistency.horizons]
           if result.best in result.noise else []}
    if plain is not None:
        row.update(plain_position_m=plain.position_m, plain_yaw_rad=plain.yaw_rad,
                   position_ratio=written.position_m / plain.position_m,
                   yaw_ratio=written.yaw_rad / plain.yaw_rad)
        row['not_dominated'] = row['position_ratio'] <= 1.0 and row['yaw_ratio'] <= 1.0
        row['gain_10pct'] = min(row['position_ratio'], row['yaw_ratio']) <= DOMINANCE_GAIN
    return row


def run(schemes: Sequence[str] = TRAIN_SEGMENTS, sim_steps: int = 150) -> dict[str, Any]:
    """Every data set under every scheme; rows in one list."""
    rows = []
    with one_blas_thread():
        for name, (drives, geometry) in datasets(sim_steps).items():
            for scheme in schemes:
                rows.append({'data': name, **score(drives, geometry, scheme)})
    return {'rows': rows}


def table(result: dict[str, Any]) -> str:
    """Return the rows as a Markdown table."""
    lines = ['| data | segments | written model | position m (written / plain) | ratio | '
             'heading rad (written / plain) | ratio | not dominated, >= 10 % in one |',
             '|---|---|---|---|---|---|---|---|']
    for r in result['rows']:
        lines.append(
            f"| {r['data']} | {r['segments']} | {r['model']} ({r['interval']}) | "
            f"{r['written_position_m']:.3f} / {r.get('plain_position_m', float('nan')):.3f} | "
            f"{r.get('position_ratio', float('nan')):.3f} | "
            f"{r['written_yaw_rad']:.3f} / {r.get('plain_yaw_rad', float('nan')):.3f} | "
            f"{r.get('yaw_ratio', float('nan')):.3f} | "
            f"{'yes' if r.get('not_dominated') and r.get('gain_10pct') else 'NO'} |")
    return '\n'.join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the schemes named on the command line (all by default) and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('schemes', nargs='*', metavar='SCHEME',
                        help=f'training-segment schemes to run, of {", ".join(TRAIN_SEGMENTS)} '
                        '(default: all)')
    schemes = tuple(parser.parse_args(argv).schemes) or TRAIN_SEGMENTS
    unknown = sorted(set(schemes) - set(TRAIN_SEGMENTS))
    if unknown:  # argparse's choices refuse an empty list with nargs='*' on Python 3.11
        parser.error(f'unknown scheme(s) {", ".join(unknown)}: choose from '
                     f'{", ".join(TRAIN_SEGMENTS)}')
    out = run(schemes)
    print(table(out))
    print(json.dumps(out['rows'], indent=1, default=str))
    return 0


if __name__ == '__main__':
    sys.exit(main())
