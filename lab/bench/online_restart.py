"""Grounds that survive a restart: drive B started from the file saved after drive A.

For each case and seed: drive A (the online study's simulator, ``lab.studies.online``) is
learned online from the fixed file and saved as ``~/save_calibration`` saves it
(:func:`skidkin_ros.core.online.save.save_learned`, then read back as the node reads it); drive
B (another seed) is then run, in one process, from four starts:

* **fixed**: the fixed calibrated file, online learning on (starting fresh);
* **active only**: the saved file without its ``online.grounds.*`` (what the save wrote before
  the remembered grounds: the active ground's parameters only);
* **grounds**: the saved file as written (every remembered ground);
* **grounds kept**: the same, with a remembered ground never forgotten (in the product, one
  not learned on yet is forgotten when a new ground starts: ``GroundBank._forget_unconfirmed``);
* **true**: the simulator's true model of the ground under the robot (the floor).

Cases (A -> B): ``alternating`` and ``long stretches`` (the same two grounds in A and B, the
study's); the worst cases, where what A remembered is wrong for B: ``third alternating`` and
``third long`` (B's second ground is a third one, slip ``THIRD`` instead of the study's), and
``effect-free`` (B on the calibration ground only).

Scores of B: eps_t, eps_th (whole drive, the study's increments over 2 m), eps_t over its first
``EARLY_M`` m, ``known at m`` (B's path until every ground B drives on has a ground in the learner
within ``KNOWN_SHARE`` of the distance between B's two true grounds, in alpha_l, alpha_r, y_l
and y_r; inf: never; effect-free: within 3 %),
and a 20 s reference dropout early in B (from ``DROP_S``): eps_t of the drive with it, and its
cost (over the same start's eps_t without). Run::

    python -m lab.bench.online_restart --seeds 3 4
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
import sys
import tempfile
import time

from lab.studies import online as study
import numpy as np
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.saved_grounds import GROUND_NAMES
from skidkin_ros.core.online import online_odometer
from skidkin_ros.core.online.save import save_learned
from skidkin_ros.sim.effects import make_effect
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate

DURATION_S = 240.0
EARLY_M = 30.0
KNOWN_SHARE = 0.3
DROP_S = 30.0
# B's third ground (slip in translation, in yaw): unlike the study's (0.25, 0.15).
THIRD = (0.40, 0.02)
SECOND = (study.SLIP, study.YAW_SLIP)
CASES = {  # name: (A's drive, B's drive, B's second ground)
    'alternating': ('alternate', 'alternate', SECOND),
    'long stretches': ('time', 'time', SECOND),
    'third alternating': ('alternate', 'alternate', THIRD),
    'third long': ('time', 'time', THIRD),
    'effect-free': ('alternate', None, None),
}
STARTS = ('fixed', 'active only', 'grounds', 'grounds kept')


def _effects(mode: str | None, ground: tuple[float, float]) -> tuple:
    if mode is None:
        return ()
    if mode == 'alternate':
        return (make_effect('terrain_regime', ground[0], mode='alternate',
                            period_m=study.PERIOD_M, yaw=ground[1]),)
    return (make_effect('terrain_regime', ground[0], mode='time', switch_frac=0.5,
                        yaw=ground[1]),)


def _ground_values(ground: tuple[float, float]) -> dict[str, float]:
    """Return the true parameters of a terrain regime's ground (slip, yaw slip)."""
    base = dict(DEFAULT_TRUE_PARAMS)
    slip, yaw = ground
    ratio = (1.0 - slip) / (1.0 - yaw)
    return {'alpha_l': base['alpha_l'] * (1 - slip), 'alpha_r': base['alpha_r'] * (1 - slip),
            'x_v': base['x_v'] / (1.0 - yaw), 'y_l': base['y_l'] * ratio,
            'y_r': base['y_r'] * ratio}


def _true_poses(sim, ground: tuple[float, float] | None, interval: str) -> np.ndarray:
    model = get_model(study.MODEL)
    geometry = sim.config.geometry
    base = dict(DEFAULT_TRUE_PARAMS)
    other = _ground_values(ground or SECOND)
    return study.ground_poses(sim, (model.bind(base, geometry), model.bind(other, geometry)),
                              interval)


def _watch(odometer) -> list:
    """Log (t_ns, every ground's values) at the start and whenever the parameters change."""
    learner = odometer.learner
    log = [(0, [g.k.copy() for g in learner.grounds])]
    step = learner.wheel_step

    def logged(t1_ns, wheels, twist):
        changed = step(t1_ns, wheels, twist)
        if changed:
            log.append((t1_ns, [g.k.copy() for g in learner.grounds]))
        return changed
    learner.wheel_step = logged
    return log


def _known_at(log: list, grounds: list[np.ndarray]) -> int | None:
    """Return the first time (ns) every true ground has a remembered one close to it, or None.

    Close: within KNOWN_SHARE of the distance between the true grounds in every slip and
    ICR parameter (alpha_l, alpha_r, y_l, y_r; x_v is hardly observable), a ground no blend
    of the two comes near.
    """
    pick = [0, 1, 3, 4]
    spread = np.abs(grounds[0] - grounds[-1])[pick] if len(grounds) > 1 else None
    for t_ns, ks in log:
        if all(any((np.abs(k - g)[pick] <= KNOWN_SHARE * spread).all() if spread is not None
                   else (np.abs(k - g)[pick] <= 0.03 * np.abs(g[pick])).all() for k in ks)
               for g in grounds):
            return t_ns
    return None


def _never() -> None:
    """Forget nothing (the 'grounds kept' start)."""


def _path_at(sim, path: np.ndarray, t_ns: int | None) -> float:
    if t_ns is None:
        return math.inf
    return float(np.interp(max(t_ns, int(sim.wheels.t_ns[0])), sim.wheels.t_ns, path))


def run_pair(case: str, seed: int, fixed: OdometryConfig, folder: Path) -> dict:
    """Learn A, save, run B from every start; return B's scores by start."""
    a_mode, b_mode, b_ground = CASES[case]
    online_fixed = OdometryConfig.from_flat({**fixed.values, 'online.enabled': True})
    sim_a = simulate(SimConfig(duration_s=DURATION_S, seed=seed,
                               effects=_effects(a_mode, SECOND)))
    odometer = online_odometer(online_fixed)
    odometer.predict(sim_a.wheels, reference=study._reference(sim_a, np.random.default_rng(seed)))
    saved_path = save_learned(online_fixed, odometer.learner, folder / f'{case}_{seed}.yaml')
    saved = OdometryConfig.from_file(saved_path)
    active_only = OdometryConfig.from_flat({k: v for k, v in saved.values.items()
                                            if k not in GROUND_NAMES})
    starts = {'fixed': online_fixed, 'active only': active_only, 'grounds': saved,
              'grounds kept': saved}
    b_seed = seed + 500
    sim_b = simulate(SimConfig(duration_s=DURATION_S, seed=b_seed,
                               effects=_effects(b_mode, b_ground or SECOND)))
    reference = study._reference(sim_b, np.random.default_rng(b_seed))
    cut = (DROP_S, DROP_S + 20.0)
    dropped = study._reference(sim_b, np.random.default_rng(b_seed), cut)
    steps = np.diff(sim_b.truth.poses[:, :2], axis=0)
    path = np.concatenate([[0.0], np.cumsum(np.hypot(steps[:, 0], steps[:, 1]))])
    early = int(np.searchsorted(path, EARLY_M))
    true_t, true_th = study._scores(sim_b, _true_poses(sim_b, b_ground, fixed['interval']))
    out = {'true': {'eps_t': float(true_t.mean()), 'eps_th': float(true_th.mean()),
                    'early': float(true_t[:early].mean())},
           'grounds A': len(odometer.learner.grounds), 'path B': float(path[-1])}
    model = get_model(study.MODEL)
    truths = [model.vector(DEFAULT_TRUE_PARAMS, fixed.geometry)]
    if b_mode is not None:
        truths.append(model.vector(_ground_values(b_ground), fixed.geometry))
    for name, config in starts.items():
        run, drop = online_odometer(config), online_odometer(config)
        if name == 'grounds kept':
            for odometer in (run, drop):
                odometer.learner._forget_unconfirmed = _never
        log = _watch(run)
        eps_t, eps_th = study._scores(sim_b, run.predict(sim_b.wheels, reference=reference).poses)
        drop_t = study._scores(sim_b, drop.predict(sim_b.wheels, reference=dropped).poses)[0]
        out[name] = {'eps_t': float(eps_t.mean()), 'eps_th': float(eps_th.mean()),
                     'early': float(eps_t[:early].mean()),
                     'known_m': _path_at(sim_b, path, _known_at(log, truths)),
                     'drop_t': float(drop_t.mean()),
                     'grounds': len(run.learner.grounds),
                     'changes': int(run.counters['online_change'])}
    return out


def table(rows: list[tuple[str, int, dict]]) -> str:
    """Return every drive B's scores by start as a markdown table."""
    lines = ['| case | seed A / B | B path m | start | eps_t m | eps_th rad | eps_t first '
             f'{EARLY_M:.0f} m | known at m | eps_t with 20 s dropout at {DROP_S:.0f} s (cost) '
             '| new grounds in B |', '|' + '---|' * 10]
    for case, seed, out in rows:
        for name in STARTS:
            r = out[name]
            lines.append(
                f'| {case} | {seed} / {seed + 500} | {out["path B"]:.0f} | {name} | '
                f'{r["eps_t"]:.4f} | {r["eps_th"]:.4f} | {r["early"]:.4f} | '
                f'{r["known_m"]:.1f} | {r["drop_t"]:.4f} '
                f'({100 * (r["drop_t"] / r["eps_t"] - 1):+.0f} %) | '
                f'{r["changes"]} |')
        t = out['true']
        lines.append(f'| {case} | {seed} / {seed + 500} | | true | {t["eps_t"]:.4f} | '
                     f'{t["eps_th"]:.4f} | {t["early"]:.4f} | | | |')
    return '\n'.join(lines)


def summary(rows: list[tuple[str, int, dict]]) -> str:
    """Per case: the mean over seeds of grounds / active only and grounds / fixed ratios."""
    lines = ['| case | seeds | eps_t grounds / active only | grounds / fixed | early eps_t '
             'grounds / active only | known at m (median): fixed, active only, grounds | '
             'dropout eps_t grounds / active only | eps_t grounds kept / active only |',
             '|' + '---|' * 8]
    for case in CASES:
        mine = [out for c, _, out in rows if c == case]
        if not mine:
            continue

        def ratio(key, a, b):
            return float(np.mean([o[a][key] / o[b][key] for o in mine]))
        unknown = [float(np.median([o[s]['known_m'] for o in mine])) for s in STARTS[:3]]
        lines.append(
            f'| {case} | {len(mine)} | {ratio("eps_t", "grounds", "active only"):.2f} | '
            f'{ratio("eps_t", "grounds", "fixed"):.2f} | '
            f'{ratio("early", "grounds", "active only"):.2f} | '
            + ', '.join(f'{u:.1f}' for u in unknown)
            + f' | {ratio("drop_t", "grounds", "active only"):.2f} | '
            f'{ratio("eps_t", "grounds kept", "active only"):.2f} |')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the cases on the seeds and print the tables."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[3, 4])
    parser.add_argument('--cases', nargs='+', default=list(CASES), choices=list(CASES))
    args = parser.parse_args(argv)
    tic = time.perf_counter()
    fixed = study.calibrated_file()
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for case in args.cases:
            for seed in args.seeds:
                rows.append((case, seed, run_pair(case, seed, fixed, Path(folder))))
                print(f'# {case} {seed} done ({time.perf_counter() - tic:.0f} s)',
                      file=sys.stderr, flush=True)
    print(table(rows))
    print()
    print(summary(rows))
    print(f'\n({time.perf_counter() - tic:.0f} s, {time.process_time():.0f} s CPU)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
