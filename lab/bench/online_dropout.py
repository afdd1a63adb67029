"""Where a 20 s reference dropout costs, and what any choice without a reference could do.

For each drive of the online study (``lab.studies.online``: the reference cut for 20 s at three
quarters of the drive, the kept poses with the same noise as without the cut), prints the
dropout's cost (the drive's eps_t with the dropout over the eps_t without), where the extra
error lies (increments starting before, during, and after the dropout, as shares of the
drive's eps_t), and bounds: the run without the dropout with, for the dropout's 20 s only, the
per-sample motion of another odometry spliced in (the true model of the ground under the robot:
an oracle; the true model of either ground held; the true model of the two grounds' average:
the best single choice that knows nothing of where the robot is, and the two grounds' predicted
twists averaged: their predictions blended rather than their parameters). Run::

    python -m lab.bench.online_dropout --case alternating --seeds 11 44 45

With ``--gyro``: the odometry fuses the simulator's 100 Hz gyro (its white noise, plus a
constant bias of ``--gyro-bias`` rad/s) in both runs (``imu.mode`` fuse), and the gyro weighs
the grounds while holding (``core/online/gyrochoice.py``); ``--no-choice`` leaves the gyro's
weighing out (the blend of the Markov chain alone, as without a gyro), for the comparison;
``--gyro-bias-sigma`` sets the file's ``imu.bias_sigma`` (the default 1e-3 is a third of the
default bias: the published NEES then shows a gyro declared better than it is).

With ``--spread F`` (alternating only): each stretch of ground lasts a length drawn uniformly
within the study's 4 m (1 +- F), a new draw per drive seed (``terrain_regime`` period_spread),
instead of exactly 4 m: a holding rule that learned "every 4 m" gains nothing there.
``--no-dwell`` runs the holding blend without its dwell model (the Markov chain alone).
``--wheel-signals`` runs no odometry: per drive, how well each wheel signal tells the ground
under the robot (the area under the ROC curve against the terrain regime's mask; 0.5: not
at all).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys

from lab.studies import online as study
import numpy as np
from skidkin_ros.core.drive import ImuSamples
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.online import online_odometer
from skidkin_ros.sim.effects import make_effect
from skidkin_ros.sim.simulate import SimConfig, simulate

DURATION_S = 240.0


def _between(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return c * dx + s * dy, -s * dx + c * dy, b[2] - a[2]


def splice(poses: np.ndarray, other: np.ndarray, i0: int, i1: int) -> np.ndarray:
    """Return ``poses`` with the per-sample motion of ``other`` in samples [i0, i1)."""
    out = poses.copy()
    for i in range(max(i0, 1), len(poses)):
        src = other if i < i1 else poses
        dx, dy, dyaw = _between(src[i - 1], src[i])
        c, s = math.cos(out[i - 1, 2]), math.sin(out[i - 1, 2])
        out[i] = (out[i - 1, 0] + c * dx - s * dy, out[i - 1, 1] + s * dx + c * dy,
                  out[i - 1, 2] + dyaw)
    return out


def _grounds() -> tuple[dict, dict]:
    return study.true_grounds()


def biased_gyro(imu: ImuSamples, bias: float) -> ImuSamples:
    """Return the simulator's gyro (white noise) with a constant bias added."""
    return dataclasses.replace(imu, yaw_rate=imu.yaw_rate + bias)


class _MeanTwist:
    """A twist source: the mean of the given bound models' predicted twists."""

    def __init__(self, *models) -> None:
        self.models = models

    def twist(self, omega_l, omega_r) -> np.ndarray:
        return np.mean([np.asarray(m.twist(omega_l, omega_r), dtype=float)
                        for m in self.models], axis=0)


def effects(case: str, seed: int, spread: float = 0.0) -> tuple:
    """Return the study's effects of ``case``; ``spread`` > 0: alternating stretches drawn."""
    if spread <= 0.0 or case != 'alternating':
        return study._effects(case)
    return (make_effect('terrain_regime', study.SLIP, mode='alternate', period_m=study.PERIOD_M,
                        period_spread=spread, period_seed=seed, yaw=study.YAW_SLIP),)


def run_drive(case: str, seed: int, fixed: OdometryConfig, at: float = 0.75,
              gyro_bias: float | None = None, bias_sigma: float | None = None,
              spread: float = 0.0) -> dict:
    """Return the dropout's cost, where it lies, and the bounds, for one drive.

    ``gyro_bias`` (rad/s): the odometry fuses the simulator's gyro with this bias; None: no gyro.
    ``bias_sigma`` (rad/s): the file's ``imu.bias_sigma`` (None: the file's, 1e-3).
    """
    sim = simulate(SimConfig(duration_s=DURATION_S, seed=seed,
                             effects=effects(case, seed, spread)))
    flat = {**fixed.values, 'online.enabled': True}
    imu = None
    if gyro_bias is not None:
        flat['imu.mode'] = 'fuse'
        if bias_sigma is not None:
            flat['imu.bias_sigma'] = bias_sigma
        imu = biased_gyro(sim.imu, gyro_bias)
    config = OdometryConfig.from_flat(flat)
    cut = (at * DURATION_S, at * DURATION_S + 20.0)
    full = online_odometer(config).predict(
        sim.wheels, imu=imu, reference=study._reference(sim, np.random.default_rng(seed)))
    dropped_odometer = online_odometer(config)
    dropped = dropped_odometer.predict(
        sim.wheels, imu=imu,
        reference=study._reference(sim, np.random.default_rng(seed), cut))
    e_full = study._scores(sim, full.poses)[0]
    e_drop = study._scores(sim, dropped.poses)[0]
    t = (sim.wheels.t_ns[:len(e_full)] - sim.start_ns) * 1e-9
    base = e_full.mean()
    out = {'case': case, 'seed': seed, 'eps_t': base, 'cost': e_drop.mean() / base - 1.0,
           'blends': dropped_odometer.counters['online_hold_blend'],
           'looks': dropped_odometer.counters['online_hold_gyro']}
    # the published pose's NEES in the dropout run (the study's: every second after the first
    # ten), over the drive and over the dropout's 20 s plus 10 s
    nees = study._nees(sim, dropped.poses, dropped.pose_covariances)
    seconds = np.arange(10.0, 10.0 + len(nees))
    near = (seconds >= cut[0]) & (seconds < cut[1] + 10.0)
    out['nees'], out['nees_dropout'] = float(nees.mean()), float(nees[near].mean())
    # increments starting 10 s before the cut reach into it (2 m at about 0.2 m/s)
    for name, lo, hi in (('before', 0.0, cut[0] - 10.0), ('during', cut[0] - 10.0, cut[1]),
                         ('after', cut[1], math.inf)):
        pick = (t >= lo) & (t < hi)
        out[name] = float((e_drop[pick] - e_full[pick]).sum() / len(e_full) / base)
    ts = (sim.wheels.t_ns - sim.start_ns) * 1e-9
    i0, i1 = int(np.searchsorted(ts, cut[0])), int(np.searchsorted(ts, cut[1]))
    model, geometry = get_model(study.MODEL), sim.config.geometry
    a, b = _grounds()
    mean = {k: 0.5 * (a[k] + b[k]) for k in a}
    bound = {name: model.bind(p, geometry) for name, p in (('a', a), ('b', b), ('mean', mean))}
    blended = _MeanTwist(bound['a'], bound['b'])
    for name, pair in (('oracle', (bound['a'], bound['b'])), ('hold first', (bound['a'],) * 2),
                       ('hold second', (bound['b'],) * 2), ('average', (bound['mean'],) * 2),
                       ('average twist', (blended, blended))):
        poses = study.ground_poses(sim, pair, fixed['interval'])
        out[name] = study._scores(sim, splice(full.poses, poses, i0, i1))[0].mean() / base - 1
    return out


def wheel_signals(case: str, seed: int, spread: float = 0.0) -> dict:
    """Return the area under the ROC curve of wheel signals against the ground, per signal."""
    from scipy import stats

    sim = simulate(SimConfig(duration_s=DURATION_S, seed=seed,
                             effects=effects(case, seed, spread)))
    trace = sim.trace
    on = np.interp(sim.wheels.t_ns, trace.t_ns, trace.masks['terrain_regime'].astype(float)) > 0.5
    left, right = np.asarray(sim.wheels.omega_l), np.asarray(sim.wheels.omega_r)
    cmd_l = np.interp(sim.wheels.t_ns, trace.t_ns, trace.cmd_l)
    cmd_r = np.interp(sim.wheels.t_ns, trace.t_ns, trace.cmd_r)
    signals = {'mean speed': np.abs(left + right) / 2, 'speed difference': right - left,
               'speed - commanded': (left + right - cmd_l - cmd_r) / 2,
               'difference - commanded': (right - left) - (cmd_r - cmd_l)}
    pairs = float(on.sum()) * float((~on).sum())
    return {name: float(stats.mannwhitneyu(v[on], v[~on]).statistic / pairs)
            for name, v in signals.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--case', default='alternating', choices=study.CASES)
    parser.add_argument('--seeds', type=int, nargs='+', default=[11, 44, 45])
    parser.add_argument('--at', type=float, default=0.75,
                        help="the dropout's start, as a share of the drive (the study's 0.75)")
    parser.add_argument('--gyro', action='store_true',
                        help='fuse the simulated gyro (imu.mode fuse) in both runs')
    parser.add_argument('--gyro-bias', type=float, default=0.003,
                        help="the gyro's constant bias (rad/s) with --gyro")
    parser.add_argument('--gyro-bias-sigma', type=float, default=None,
                        help="with --gyro: the file's imu.bias_sigma (default: the file's, 1e-3)")
    parser.add_argument('--no-choice', action='store_true',
                        help="with --gyro: leave the gyro's weighing of the grounds out")
    parser.add_argument('--spread', type=float, default=0.0,
                        help='alternating: stretch lengths drawn within 4 m (1 +- SPREAD)')
    parser.add_argument('--no-dwell', action='store_true',
                        help="leave the holding blend's dwell model out (the Markov chain alone)")
    parser.add_argument('--wheel-signals', action='store_true',
                        help='no odometry: how well wheel signals tell the grounds apart (AUC)')
    args = parser.parse_args(argv)
    if args.wheel_signals:
        for seed in args.seeds:
            auc = wheel_signals(args.case, seed, args.spread)
            print(f'seed {seed}: AUC ' + ', '.join(f'{k} {v:.3f}' for k, v in auc.items()))
        return 0
    if args.no_dwell:
        from skidkin_ros.core.online import holding
        holding.HoldingBlend._dwell_plan = lambda self, grounds: None
    if args.no_choice:
        from skidkin_ros.core.online.gyrochoice import GyroChoice
        GyroChoice._gyro_weigh = lambda self, t1_ns, plan, travel, weights: weights
    fixed = study.calibrated_file()
    print('| case | seed | eps_t (m) | dropout cost | of which before / during / after | '
          'oracle | hold first ground | hold second | average model | blends | '
          'NEES drive / dropout + 10 s |')
    print('|' + '---|' * 11)
    for seed in args.seeds:
        r = run_drive(args.case, seed, fixed, args.at,
                      args.gyro_bias if args.gyro else None, args.gyro_bias_sigma, args.spread)
        print(f"| {r['case']} | {seed} | {r['eps_t']:.4f} | {100 * r['cost']:+.1f} % | "
              f"{100 * r['before']:+.1f} / {100 * r['during']:+.1f} / {100 * r['after']:+.1f} |"
              f" {100 * r['oracle']:+.1f} % | {100 * r['hold first']:+.1f} % | "
              f"{100 * r['hold second']:+.1f} % | {100 * r['average']:+.1f} % | "
              f"{100 * r['average twist']:+.1f} % | "
              f"{r['blends']} ({r['looks']}) | {r['nees']:.2f} / {r['nees_dropout']:.2f} |",
              flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
