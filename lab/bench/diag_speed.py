"""Diagnosis speed, old against new in one run: the same drives, the same machine, the same jobs.

``python lab/bench/diag_speed.py --km 0.5 --fd --old-commit 4a5fc0e [--old CHECKOUT]``
diagnoses the drives of the diagnosis benchmark (:mod:`diag_bench`: true model edd_asymmetric,
base edd_symmetric at its defaults) with this checkout's code and, in a subprocess each, with
every older version's (its own default candidates): a checkout (``--old``) or a commit of this
repository (``--old-commit``: its package is extracted with ``git archive`` into a temporary
folder), and writes one JSON line: per variant the wall time and the process CPU time (this
process and its worker processes: what the machine's load changes least) per km, and the ratios
old / new. ``--fd`` adds this checkout with the fits' finite-difference Jacobians
(``diagnosis.state.ANALYTIC_JACOBIAN = False``): what the exact Jacobians alone gain, with
everything else equal. Each variant runs in a fresh interpreter, one after the other.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import resource
import subprocess
import sys
import tempfile
import time

HERE = Path(__file__).resolve().parent


def _cpu_s() -> float:
    """Return the CPU seconds (user + system) of this process and its finished children."""
    total = 0.0
    for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
        usage = resource.getrusage(who)
        total += usage.ru_utime + usage.ru_stime
    return total


def timed(km: float, jobs: int, finite_differences: bool = False) -> dict:
    """Diagnose the first ``km`` of the benchmark drives with the code on sys.path."""
    sys.path.insert(0, str(HERE))
    from calib_bench import first_km, simulate_drives
    from skidkin_ros.core.calibration.diagnosis import diagnose, DiagnosisOptions
    from skidkin_ros.sim import SimConfig
    if finite_differences:
        from skidkin_ros.core.calibration.diagnosis import state
        state.ANALYTIC_JACOBIAN = False
    drives = first_km(simulate_drives(km, 120.0, seed=300), km)
    path_km = sum(float(d.truth.path_length()[-1]) for d in drives) / 1000.0
    cpu = _cpu_s()
    tic = time.perf_counter()
    result = diagnose(drives, None, SimConfig().geometry, {'edd_symmetric': {}},
                      'edd_symmetric', DiagnosisOptions(holdout_mode='time'), jobs=jobs)
    seconds = time.perf_counter() - tic
    cpu = _cpu_s() - cpu
    final = result.final
    return {'km': path_km, 'seconds': seconds, 's_per_km': seconds / path_km,
            'cpu_s': cpu, 'cpu_s_per_km': cpu / path_km,
            'found': list(result.extensions), 'eps_t': result.steps[-1].stats_t.median,
            'base_values': dict(getattr(final, 'base_values', {})),
            'ext_values': {name: dict(values)
                           for name, values in getattr(final, 'ext_values', {}).items()
                           if name in result.extensions}}


def _in_subprocess(checkout: Path | None, km: float, jobs: int, fd: bool = False) -> dict:
    """Run :func:`timed` in a fresh interpreter, on ``checkout``'s code (None: this one's)."""
    env = dict(os.environ)
    if checkout is not None:
        env['PYTHONPATH'] = str(checkout)
    command = [sys.executable, str(HERE / 'diag_speed.py'), '--one', '--km', str(km),
               '--jobs', str(jobs)] + (['--fd'] if fd else [])
    run = subprocess.run(command, env=env, check=True, capture_output=True, text=True,
                         cwd=str(checkout or HERE.parent.parent))
    return json.loads(run.stdout.strip().splitlines()[-1])


def _at_commit(commit: str, folder: Path) -> Path:
    """Extract the package as it was at ``commit`` into ``folder``; return the folder."""
    repo = HERE.parent.parent
    archive = subprocess.run(['git', '-C', str(repo), 'archive', commit, 'skidkin_ros'],
                             check=True, capture_output=True).stdout
    subprocess.run(['tar', '-x', '-C', str(folder)], input=archive, check=True)
    return folder


def compare(km: float, jobs: int, olds: list[Path], fd: bool,
            commits: list[str] = ()) -> dict:
    """Time this checkout, then each older one (and the finite-difference variant): one dict."""
    out = {'new': _in_subprocess(None, km, jobs)}
    variants = {}
    if fd:
        variants['finite_differences'] = _in_subprocess(None, km, jobs, fd=True)
    for old in olds:
        variants[str(old)] = _in_subprocess(old, km, jobs)
    for commit in commits:
        with tempfile.TemporaryDirectory(prefix='skidkin_old_') as folder:
            variants[f'commit {commit}'] = _in_subprocess(_at_commit(commit, Path(folder)), km,
                                                          jobs)
    for name, row in variants.items():
        row['speedup_wall'] = row['s_per_km'] / out['new']['s_per_km']
        row['speedup_cpu'] = row['cpu_s_per_km'] / out['new']['cpu_s_per_km']
    out['old'] = variants
    out['loadavg'] = ' '.join(f'{v:.2f}' for v in os.getloadavg())
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--km', type=float, default=0.5)
    parser.add_argument('--jobs', type=int, default=2)
    parser.add_argument('--old', type=Path, action='append', default=[],
                        help='an older checkout to compare with (repeatable)')
    parser.add_argument('--old-commit', action='append', default=[], metavar='COMMIT',
                        help='a commit of this repository to compare with (repeatable)')
    parser.add_argument('--fd', action='store_true',
                        help="also this checkout with the fits' finite-difference Jacobians")
    parser.add_argument('--one', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        sys.stdout.write(json.dumps(timed(args.km, args.jobs, args.fd)) + '\n')
        return 0
    out = compare(args.km, args.jobs, args.old, args.fd, args.old_commit)
    sys.stdout.write(json.dumps(out) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
