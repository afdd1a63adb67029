"""Diagnosis speed, old against new in one run: the same drives, the same machine, the same jobs.

``python lab/bench/diag_speed.py --km 0.5 --old OLDER_CHECKOUT`` diagnoses the drives of the
diagnosis benchmark (:mod:`diag_bench`: true model edd_asymmetric, base edd_symmetric at its
defaults) with this checkout's code and, in a subprocess, with the older checkout's (its default
candidates: the sparse fallback instead of the residual model), and writes s/km of each and their
ratio as one JSON line.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import subprocess
import sys
import time

HERE = Path(__file__).resolve().parent


def timed(km: float, jobs: int) -> dict:
    """Diagnose the first ``km`` of the benchmark drives with the code on sys.path."""
    sys.path.insert(0, str(HERE))
    from calib_bench import first_km, simulate_drives
    from skidkin_ros.core.calibration.diagnosis import diagnose, DiagnosisOptions
    from skidkin_ros.sim import SimConfig
    drives = first_km(simulate_drives(km, 120.0, seed=300), km)
    path_km = sum(float(d.truth.path_length()[-1]) for d in drives) / 1000.0
    tic = time.perf_counter()
    result = diagnose(drives, None, SimConfig().geometry, {'edd_symmetric': {}},
                      'edd_symmetric', DiagnosisOptions(holdout_mode='time'), jobs=jobs)
    seconds = time.perf_counter() - tic
    return {'km': path_km, 'seconds': seconds, 's_per_km': seconds / path_km,
            'found': list(result.extensions), 'eps_t': result.steps[-1].stats_t.median}


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument('--km', type=float, default=0.5)
    parser.add_argument('--jobs', type=int, default=2)
    parser.add_argument('--old', type=Path, help='an older checkout to compare with')
    parser.add_argument('--one', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        sys.stdout.write(json.dumps(timed(args.km, args.jobs)) + '\n')
        return 0
    out = {'new': timed(args.km, args.jobs)}
    if args.old is not None:
        env = dict(os.environ, PYTHONPATH=str(args.old))
        run = subprocess.run([sys.executable, str(HERE / 'diag_speed.py'), '--one', '--km',
                              str(args.km), '--jobs', str(args.jobs)], env=env, check=True,
                             capture_output=True, text=True, cwd=str(args.old))
        out['old'] = json.loads(run.stdout.strip().splitlines()[-1])
        out['speedup'] = out['old']['s_per_km'] / out['new']['s_per_km']
    sys.stdout.write(json.dumps(out) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
