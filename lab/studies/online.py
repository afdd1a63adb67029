"""Online calibration study: fixed file, online learning and the true model, side by side.

Simulated drives (``edd_asymmetric`` truth, 20 Hz wheels with white encoder noise, a 10 Hz
reference: the exact truth plus ``REF_SIGMA_M`` / ``REF_SIGMA_RAD`` of white noise, as a lidar
odometry gives) on three kinds of ground:

* ``long stretches``: the calibration ground, then from half the drive on a ground where the
  forward speed loses ``SLIP`` and the yaw rate ``YAW_SLIP`` (``terrain_regime`` mode time with
  the ``yaw`` option): tens of metres of each;
* ``alternating``: the same two grounds alternating every ``PERIOD_M`` metres of path
  (``terrain_regime`` mode alternate);
* ``effect-free``: the calibration ground throughout.

Three odometries run on the same wheel samples: the **fixed** file (``edd_asymmetric`` fitted by
the calibrator, :func:`skidkin_ros.core.calibration.weighting.fit_model_iterated`, on two
effect-free drives, with its noise: what a user runs today), **online** (the same file with
``online.enabled``, learning from the reference through the node's own odometer) and the **true**
model (the simulator's parameters of the ground under the robot at each sample: the floor).

Scores (all on the whole drive): ε_t and ε_θ, the mean position and heading error of the
odometry's increments over 2 m of true path (:func:`skidkin_ros.sim.accuracy.increment_errors`,
the calibrator's comparison); metres to learn a new ground (long stretches: the true path from
the change to the first 2 m increment from which the next 40 (2 s of driving) average within
1.5x the true model's); the cost of a 20 s reference dropout (the drive's ε_t with the
reference cut for 20 s at three quarters of the drive, over the ε_t without); the NEES of the
published pose (x, y, yaw) against its published covariance at every second after the first
ten, whole drive from the start (mean, and the share inside the 95 % chi2 region). Run::

    python -m lab.bench.online_study

(about a minute on one core).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import math
from typing import Sequence

import numpy as np
from scipy import stats

from skidkin_ros.core.calibration.noise_fit import calibrate_noise
from skidkin_ros.core.calibration.segments import (HorizonOptions, SegmentOptions,
                                                   usable_segments)
from skidkin_ros.core.calibration.weighting import fit_model_iterated
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.integrator import StreamingIntegrator
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.core.online import online_odometer
from skidkin_ros.sim.accuracy import increment_errors
from skidkin_ros.sim.effects import make_effect
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate, Simulation

__all__ = ['CASES', 'CaseResult', 'calibrated_file', 'online_settings', 'run_case', 'run_study',
           'table']

SLIP, YAW_SLIP = 0.25, 0.15
PERIOD_M = 4.0
REF_SIGMA_M, REF_SIGMA_RAD = 0.01, 0.003
CASES = ('long stretches', 'alternating', 'effect-free')
MODEL = 'edd_asymmetric'
CHI2_95_3 = float(stats.chi2.ppf(0.95, 3))
# Increments (one per wheel sample: 2 s at 20 Hz) that must average within 1.5x the truth's.
LEARNED_RUN = 40


def _effects(case: str) -> tuple:
    if case == 'long stretches':
        return (make_effect('terrain_regime', SLIP, mode='time', switch_frac=0.5,
                            yaw=YAW_SLIP),)
    if case == 'alternating':
        return (make_effect('terrain_regime', SLIP, mode='alternate', period_m=PERIOD_M,
                            yaw=YAW_SLIP),)
    return ()


def online_settings(parser, items: Sequence[str]) -> dict[str, float]:
    """Return the benches' ``--set online.NAME=VALUE`` items as a dict (a parser error else)."""
    settings = {}
    for item in items:
        name, _, value = item.partition('=')
        if not name.startswith('online.') or not value:
            parser.error(f'--set {item!r}: expected online.NAME=VALUE')
        settings[name] = float(value)
    return settings


def calibrated_file(seeds: Sequence[int] = (101, 102), held_out: int = 103,
                    duration_s: float = 150.0, interval: str | None = None) -> OdometryConfig:
    """Return the fixed file: the calibrator's fit (two drives) and noise (a third one).

    ``interval``: the sample-interval convention fitted and written (None: the default,
    ``ending``, as the studies have always run). The simulator's speeds are sampled at the stamp,
    for which ``midpoint`` is exact (what ``skidkin calibrate`` chooses on these drives);
    under ``ending`` the wheels' motion leads the truth by half a wheel period (25 ms at 20 Hz),
    which a delay measured against the wheels reads as a reference that late.
    """
    drives = [simulate(SimConfig(duration_s=duration_s, seed=s)).drive(f'cal{s}')
              for s in seeds]
    check = [simulate(SimConfig(duration_s=duration_s, seed=held_out)).drive('held_out')]
    geometry = SimConfig().geometry
    train = HorizonOptions().train_segments()
    evaluate = SegmentOptions()
    if interval is not None:
        train, evaluate = replace(train, interval=interval), replace(evaluate, interval=interval)
    segments = usable_segments(drives, train, 'training')
    fit = fit_model_iterated(MODEL, geometry, segments)
    horizons = {h: usable_segments(check, replace(evaluate, horizon_m=h), 'evaluation')
                for h in (0.5, 1.0, 2.0, 4.0)}
    noise = calibrate_noise(MODEL, fit.values, geometry, horizons[2.0],
                            {h: seg for h, seg in horizons.items() if h != 2.0},
                            fit.covariance).noise
    flat = {'model': MODEL, 'robot': 'sim', 'models.edd_asymmetric.noise.calibrated': True,
            **{f'models.{MODEL}.{k}': v for k, v in fit.values.items()},
            **{f'models.{MODEL}.noise.{k}': v for k, v in noise.as_dict().items()},
            f'models.{MODEL}.parameter_covariance': fit.covariance.ravel().tolist()}
    if interval is not None:
        flat['interval'] = interval
    return OdometryConfig.from_flat(flat)


def true_grounds() -> tuple[dict[str, float], dict[str, float]]:
    """Return the true parameters of the two grounds (MODEL's): the simulator's, and the other.

    The other ground loses SLIP of its forward speed and YAW_SLIP of its yaw rate: both
    alphas scale by 1 - SLIP, and x_v, y_l, y_r so that v / omega keeps the ratio of the two.
    """
    base = dict(DEFAULT_TRUE_PARAMS)
    ratio = (1.0 - SLIP) / (1.0 - YAW_SLIP)
    other = {'alpha_l': base['alpha_l'] * (1 - SLIP), 'alpha_r': base['alpha_r'] * (1 - SLIP),
             'x_v': base['x_v'] / (1.0 - YAW_SLIP), 'y_l': base['y_l'] * ratio,
             'y_r': base['y_r'] * ratio}
    return base, other


def _true_poses(sim: Simulation, interval: str) -> np.ndarray:
    """Integrate the wheels with the true parameters of the ground under the robot."""
    model = get_model(MODEL)
    geometry = sim.config.geometry
    base, other = true_grounds()
    return ground_poses(sim, (model.bind(base, geometry), model.bind(other, geometry)),
                        interval)


def ground_poses(sim: Simulation, sources: Sequence, interval: str) -> np.ndarray:
    """Integrate the wheels with sources[0] off the terrain regime's second ground, [1] on it."""
    mask = sim.trace.masks.get('terrain_regime')
    on = (np.zeros(len(sim.wheels), bool) if mask is None else
          np.interp(sim.wheels.t_ns, sim.trace.t_ns, mask.astype(float)) > 0.5)
    integrator = StreamingIntegrator(sources[0], None, interval)
    poses = np.empty((len(sim.wheels), 3))
    current = 0
    for i, (t, left, right) in enumerate(zip(sim.wheels.t_ns.tolist(), sim.wheels.omega_l,
                                             sim.wheels.omega_r)):
        if int(on[i]) != current:
            current = int(on[i])
            integrator.set_source(sources[current])
        poses[i] = integrator.step(t, left, right).pose
    return poses


def _reference(sim: Simulation, rng: np.random.Generator,
               dropout: tuple[float, float] | None = None) -> PoseTrack:
    """Return the 10 Hz reference; ``dropout`` (s from the start): its poses left out.

    The noise is drawn for every pose before the dropout's are left out: the poses kept carry
    the same noise as without the dropout, so the dropout's cost is the dropout's alone (drawn
    after the cut, the kept poses' noise differed along the whole drive, and that alone moved
    eps_t by up to +22 % on some drives).
    """
    t = np.arange(sim.start_ns, sim.end_ns, 100_000_000)
    truth = sim.truth_at(t)
    n = len(t)
    track = PoseTrack(t, truth.x + rng.normal(0, REF_SIGMA_M, n),
                      truth.y + rng.normal(0, REF_SIGMA_M, n),
                      truth.yaw + rng.normal(0, REF_SIGMA_RAD, n))
    if dropout is None:
        return track
    rel = (t - sim.start_ns) * 1e-9
    keep = (rel < dropout[0]) | (rel >= dropout[1])
    return PoseTrack(t[keep], track.x[keep], track.y[keep], track.yaw[keep])


def _scores(sim: Simulation, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    track = PoseTrack(sim.wheels.t_ns, poses[:, 0], poses[:, 1], poses[:, 2])
    err = increment_errors(track, sim.pose_at, horizon_m=2.0)
    return err.position_m, err.yaw_rad


def _nees(sim: Simulation, poses: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """NEES of the published pose at every second after the first ten (drive from the start)."""
    t = (sim.wheels.t_ns - sim.start_ns) * 1e-9
    pick = np.nonzero((t >= 10.0) & (np.mod(np.round(t * 20), 20) == 0))[0]
    truth = sim.truth.poses
    out = []
    for i in pick:
        err = truth[i] - poses[i]
        err[2] = (err[2] + math.pi) % (2 * math.pi) - math.pi
        cov = covs[i][np.ix_([0, 1, 5], [0, 1, 5])]
        out.append(float(err @ np.linalg.solve(cov, err)))
    return np.array(out)


def _learned_m(sim: Simulation, online_t: np.ndarray, true_t: np.ndarray) -> float:
    """Path (m) from the change to where online's increments are within 1.5x the truth's."""
    path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(sim.truth.poses[:, :2],
                                                              axis=0).T))])
    switch = int(np.searchsorted(sim.wheels.t_ns, sim.start_ns + 0.5 * sim.config.duration_s
                                 * 1e9))
    start = int(np.searchsorted(np.arange(len(online_t)), switch))
    for i in range(start, len(online_t) - LEARNED_RUN):
        if (online_t[i:i + LEARNED_RUN].mean()
                <= 1.5 * true_t[i:i + LEARNED_RUN].mean() + 0.005):
            return float(path[min(i, len(path) - 1)] - path[switch])
    return math.inf


@dataclass
class CaseResult:
    """The scores of one drive: per odometry, eps_t, eps_th (m, rad) and more."""

    case: str
    seed: int
    eps_t: dict
    eps_th: dict
    learned_m: float
    dropout_ratio: float
    nees_mean: float
    nees_inside: float
    nees_fixed: float
    length_m: float


def run_case(case: str, seed: int, fixed: OdometryConfig, duration_s: float = 240.0
             ) -> CaseResult:
    """Run the three odometries on one simulated drive of ``case``."""
    sim = simulate(SimConfig(duration_s=duration_s, seed=seed, effects=_effects(case)))
    rng = np.random.default_rng(seed)
    online_config = OdometryConfig.from_flat({**fixed.values, 'online.enabled': True})
    reference = _reference(sim, rng)
    odometer = online_odometer(online_config)
    online = odometer.predict(sim.wheels, reference=reference)
    plain = Odometer.from_config(fixed).predict(sim.wheels)
    true = _true_poses(sim, fixed['interval'])
    scores = {name: _scores(sim, poses) for name, poses in
              (('fixed', plain.poses), ('online', online.poses), ('true', true))}
    cut = (0.75 * duration_s, 0.75 * duration_s + 20.0)
    dropped = online_odometer(online_config).predict(
        sim.wheels, reference=_reference(sim, np.random.default_rng(seed), cut))
    eps_drop = _scores(sim, dropped.poses)[0].mean()
    nees = _nees(sim, online.poses, online.pose_covariances)
    nees_fixed = _nees(sim, plain.poses, plain.pose_covariances)
    learned = (_learned_m(sim, scores['online'][0], scores['true'][0])
               if case == 'long stretches' else math.nan)
    return CaseResult(case, seed, {k: float(v[0].mean()) for k, v in scores.items()},
                      {k: float(v[1].mean()) for k, v in scores.items()}, learned,
                      float(eps_drop / scores['online'][0].mean()), float(nees.mean()),
                      float((nees <= CHI2_95_3).mean()), float(nees_fixed.mean()),
                      float(sim.truth.path_length()[-1]))


def run_study(seeds: dict | None = None, duration_s: float = 240.0,
              interval: str | None = None) -> list[CaseResult]:
    """Run every case on its seeds with one calibrated file (``interval``: its convention)."""
    seeds = seeds or {'long stretches': (1, 2), 'alternating': (3, 4),
                      'effect-free': (5, 6, 7)}
    fixed = calibrated_file(interval=interval)
    return [run_case(case, seed, fixed, duration_s) for case in CASES
            for seed in seeds[case]]


def table(results: list[CaseResult]) -> str:
    """Return the results as a markdown table."""
    lines = ['| case | seed | path m | eps_t fixed / online / true (m) | eps_th fixed / online / '
             'true (rad) | online/fixed eps_t | online/true eps_t | learned in m | 20 s '
             'dropout cost | NEES online: mean (95 % inside) | NEES fixed: mean |',
             '|' + '---|' * 11]
    for r in results:
        lines.append(
            f'| {r.case} | {r.seed} | {r.length_m:.0f} | {r.eps_t["fixed"]:.4f} / '
            f'{r.eps_t["online"]:.4f} / {r.eps_t["true"]:.4f} | {r.eps_th["fixed"]:.4f} / '
            f'{r.eps_th["online"]:.4f} / {r.eps_th["true"]:.4f} | '
            f'{r.eps_t["online"] / r.eps_t["fixed"]:.2f} | '
            f'{r.eps_t["online"] / r.eps_t["true"]:.2f} | {r.learned_m:.1f} | '
            f'{100 * (r.dropout_ratio - 1):+.1f} % | {r.nees_mean:.2f} '
            f'({100 * r.nees_inside:.0f} %) | {r.nees_fixed:.2f} |')
    return '\n'.join(lines)
