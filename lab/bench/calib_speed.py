"""Calibration time: today's code, the earlier path and the issue-time code, in the same run.

``skidkin calibrate`` runs :func:`~skidkin_ros.core.calibration.pipeline.calibrate_interval`.
Three codes calibrate the same drives (simulated once here, handed over as a pickle):

- ``today``: this checkout, as the CLI runs it (``interval_search='fits'``, forked workers, one
  per usable CPU);
- ``earlier``: this checkout with the earlier path kept as an option (``interval_search='full'``,
  ``jobs=1``: the whole recipe under every sample-interval convention, one model after the
  other). It shares today's lower-level code (the gyro fit, the odometer), so it is not the
  issue-time code;
- ``issue``: the code of an older commit (default ``ISSUE_COMMIT``, exported with ``git
  archive`` when this is a git checkout; ``--old DIR`` names a copy instead), its own
  ``calibrate_interval`` with its own defaults.

Each runs in a fresh Python process (the same interpreter, one BLAS thread, as the CLI), timed
from inside around the calibration alone: wall seconds and process CPU seconds (the process and
its forked workers; CPU time moves less than wall time on a shared machine). The three are run
in turn (issue, earlier, today, then again for more rounds), so the ratios hold under a
machine's changing load; the median of each is reported. ``today`` and ``earlier`` must write
the same model and values (``same_result``); the issue-time code had other defaults (segments,
roc), so its result is reported, not compared.

    PYTHONPATH=. python lab/bench/calib_speed.py --km 2
"""

from __future__ import annotations

import argparse
import io
import json
import os
from pathlib import Path
import pickle
import statistics
import subprocess
import sys
import tarfile
import tempfile
from typing import Any, Sequence

ISSUE_COMMIT = '4a5fc0e'   # the commit the calibration-time goal was measured against
CODES = ('issue', 'earlier', 'today')


def _child(drives_path: str, how: str, options_json: str) -> None:
    """Calibrate the pickled drives with the skidkin_ros on sys.path; print one JSON line."""
    import resource
    import time

    from skidkin_ros.core.calibration.pipeline import calibrate_interval, CalibrationOptions
    from skidkin_ros.core.parallel import one_blas_thread
    from skidkin_ros.sim import SimConfig

    def cpu_s() -> float:
        own = resource.getrusage(resource.RUSAGE_SELF)
        kids = resource.getrusage(resource.RUSAGE_CHILDREN)
        return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime

    with open(drives_path, 'rb') as handle:
        drives = pickle.load(handle)
    kwargs: dict[str, Any] = {}
    if how == 'earlier':
        kwargs['interval_search'] = 'full'
    options = CalibrationOptions(**json.loads(options_json), **(
        {'jobs': 1} if how == 'earlier' else {}))
    with one_blas_thread():
        cpu0, tic = cpu_s(), time.perf_counter()
        result = calibrate_interval(list(drives), None, SimConfig().geometry, options, **kwargs)
        wall, cpu = time.perf_counter() - tic, cpu_s() - cpu0
    print(json.dumps({'wall_s': wall, 'cpu_s': cpu, 'best': result.best,
                      'interval': result.options.interval,
                      'values': result.fits[result.best].values,
                      'fit_s': sum(f.seconds for f in result.fits.values())}))


def _run_child(tree: Path, drives_path: Path, how: str, options: dict[str, Any]
               ) -> dict[str, Any]:
    done = subprocess.run([sys.executable, str(Path(__file__).resolve()), '--child',
                           str(drives_path), how, json.dumps(options)],
                          env={**os.environ, 'PYTHONPATH': str(tree)},
                          capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f'{how} calibration failed:\n{done.stderr[-2000:]}')
    return json.loads(done.stdout.strip().splitlines()[-1])


def export_commit(commit: str, folder: Path) -> Path | None:
    """Export the skidkin_ros package of ``commit`` into ``folder``; None without git/commit."""
    repo = Path(__file__).resolve().parents[2]
    done = subprocess.run(['git', '-C', str(repo), 'archive', '--format=tar', commit,
                           'skidkin_ros'], capture_output=True, check=False)
    if done.returncode != 0:
        return None
    with tarfile.open(fileobj=io.BytesIO(done.stdout)) as tar:
        tar.extractall(folder, filter='data')
    return folder


def before_after(drives: Sequence[Any], options: dict[str, Any], rounds: int = 1,
                 old_tree: Path | None = None, old_commit: str | None = ISSUE_COMMIT
                 ) -> dict[str, Any]:
    """Time today's, the earlier path's and (when available) the issue-time calibration.

    ``options``: CalibrationOptions keyword arguments every code understands (the hold-out);
    ``old_tree``: a folder holding an older ``skidkin_ros``; without it, ``old_commit`` is
    exported (None: the issue-time code is not run).
    """
    import skidkin_ros
    from skidkin_ros.core.parallel import usable_cpus

    today_tree = Path(skidkin_ros.__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory(prefix='skidkin_speed_') as tmp:
        drives_path = Path(tmp) / 'drives.pkl'
        drives_path.write_bytes(pickle.dumps(list(drives)))
        if old_tree is None and old_commit:
            old_tree = export_commit(old_commit, Path(tmp) / 'old')
        trees = {'issue': old_tree, 'earlier': today_tree, 'today': today_tree}
        runs: dict[str, list[dict[str, Any]]] = {code: [] for code in CODES if trees[code]}
        issue_error = None
        for _ in range(rounds):
            for code in list(runs):
                try:
                    runs[code].append(_run_child(trees[code], drives_path, code, options))
                except RuntimeError as err:
                    if code != 'issue':
                        raise
                    issue_error = str(err)[-500:]   # older code on data it cannot take
                    del runs[code]
    out: dict[str, Any] = {'rounds': rounds, 'cpus': usable_cpus(), 'issue_error': issue_error,
                           'issue_code': (str(old_commit) if old_tree is not None
                                          and old_commit else None)}
    for code, found in runs.items():
        out[f'{code}_s'] = statistics.median(r['wall_s'] for r in found)
        out[f'{code}_cpu_s'] = statistics.median(r['cpu_s'] for r in found)
    earlier, today = runs['earlier'][-1], runs['today'][-1]
    out.update(ratio=out['earlier_s'] / out['today_s'],
               cpu_ratio=out['earlier_cpu_s'] / out['today_cpu_s'],
               same_result=(earlier['best'], earlier['interval'], earlier['values'])
               == (today['best'], today['interval'], today['values']),
               best=today['best'], interval=today['interval'], fit_s_today=today['fit_s'])
    if 'issue' in runs:
        issue = runs['issue'][-1]
        out.update(issue_ratio=out['issue_s'] / out['today_s'],
                   issue_cpu_ratio=out['issue_cpu_s'] / out['today_cpu_s'],
                   issue_best=issue['best'], issue_interval=issue['interval'])
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Simulate ``--km`` of drives and print the three codes' times (module docstring)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ['--child']:
        _child(*argv[1:4])
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--km', type=float, default=2.0, help='km of drives (default 2)')
    parser.add_argument('--rounds', type=int, default=1, help='rounds of the three (default 1)')
    parser.add_argument('--old', type=Path, help='a folder holding an older skidkin_ros '
                        f'(default: commit {ISSUE_COMMIT} exported from this checkout)')
    parser.add_argument('--old-commit', default=ISSUE_COMMIT,
                        help='the commit to export when --old is not given ("" : none)')
    args = parser.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from calib_bench import first_km, simulate_drives

    drives = first_km(simulate_drives(args.km, 600.0), args.km)
    path_km = sum(float(d.truth.path_length()[-1]) for d in drives) / 1000.0
    out = {'km': path_km, **before_after(drives, {'holdout_mode': 'time',
                                                  'holdout_block_s': 60.0},
                                         args.rounds, args.old, args.old_commit or None)}
    print(json.dumps(out, indent=1))
    print(summary(out))
    return 0


def summary(out: dict[str, Any]) -> str:
    """One paragraph: each code's wall and CPU seconds and the ratios."""
    lines = [f'{out["km"]:.2f} km, {out["cpus"]} CPUs, median of {out["rounds"]} round(s):']
    for code in CODES:
        if f'{code}_s' in out:
            lines.append(f'  {code:8s} {out[code + "_s"]:7.2f} s wall  '
                         f'{out[code + "_cpu_s"]:7.2f} s CPU')
    lines.append(f'  earlier / today: {out["ratio"]:.2f}x wall, {out["cpu_ratio"]:.2f}x CPU; '
                 f'same written model and values: {out["same_result"]}')
    if 'issue_ratio' in out:
        lines.append(f'  issue-time ({out["issue_code"]}) / today: {out["issue_ratio"]:.2f}x '
                     f'wall, {out["issue_cpu_ratio"]:.2f}x CPU')
    return '\n'.join(lines)


if __name__ == '__main__':
    sys.exit(main())
