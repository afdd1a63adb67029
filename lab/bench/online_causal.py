"""The causal floor of the long stretches: the offline calibrator refitted on what is seen so far.

``lab.bench.online_floor`` fits each ground on its whole stretch (non-causal: the first metres
of a ground run with parameters fitted on metres not driven yet). No odometry that publishes as
it goes can do that. This bench computes the **causal floor**: an oracle that knows the exact
instant of the change of ground, but at every wheel sample runs the parameters the offline
calibrator (:func:`fit_model_iterated`, the calibrator's training segments and weighting)
fits on the *current ground's* reference data up to that sample:

* the ground's reference poses and wheel samples from the change (or the drive's start) on are
  cut into the calibrator's training segments; each new segment, once its end pose is seen,
  triggers a refit on all the ground's segments so far (a fit needs ``p + 1`` segments: 6 for
  ``edd_asymmetric``), used from the next wheel step on; a fit the calibrator marks invalid
  (not converged, on a bound, a parameter unobservable) is not taken: the parameters in force
  stay;
* before the first fit of a ground, the start: the first ground starts from the fixed file
  (what the online odometry starts from); the new ground from **previous** (the first ground's
  last causal fit: what a learner that knows a change happened, but nothing of the new ground,
  has) or **true** (the simulator's parameters of the new ground: an optimistic start, a
  perfect prior). Variants (columns):

  - *causal previous*, *causal true*: both grounds refitted causally, the new one started
    as said;
  - *file, causal true*: the first ground (the calibration's own) runs the fixed file
    throughout, the new one is refitted causally from the true start: what a learner of
    these data gets when handed the new ground's parameters at the change (optimistic; not
    a strict bound: blending that start with the data, as a prior, would do a little better);
  - *file, causal prior*: the first ground the file, the new one a data-only causal refit
    (:func:`prior_fits`): a MAP fit (Gauss-Newton steps kept inside the parameters'
    ranges) of the new ground's segments so far with the online learner's new-ground prior
    (the file's values, ``online.prior_sigma`` of each parameter's typical magnitude),
    refitted at every new segment and, like the online learner's probes, every ``PROBE_M``
    or ``PROBE_RAD`` inside one (the segment in progress as one more segment), no
    forgetting: a learner that knows the change's instant but nothing of the new ground.
    The calibrator itself cannot start a ground before p + 1 segments and has no prior, so
    *causal previous* runs the old ground's parameters for the first 2.9-13.0 m (27 drives).

It is scored over the whole drive like the study (ε_t, ε_θ over 2 m increments of true path,
:mod:`lab.studies.online`), beside online, the non-causal floor (each ground fitted on its
whole stretch of the same reference) and the true model, and its excess over the true model is
split like ``lab.bench.online_budget`` (before the change, straddling it, the first
``--learn-m`` metres after it, the rest). Run::

    python -m lab.bench.online_causal --seeds 1 2 8 9 --jobs 2
"""

from __future__ import annotations

import argparse
from concurrent.futures import ProcessPoolExecutor
import sys
from typing import Sequence

from lab.studies import online as study
import numpy as np

from skidkin_ros.core.calibration.fitting import parameter_scales, segment_errors
from skidkin_ros.core.calibration.noise_fit import (parameter_sensitivity, segment_covariances,
                                                    segment_motion)
from skidkin_ros.core.calibration.segments import cut_segments, HorizonOptions, usable_segments
from skidkin_ros.core.calibration.weighting import fit_model_iterated
from skidkin_ros.core.drive import Drive, PoseTrack, WheelSamples
from skidkin_ros.core.kinematics.models import BoundModel, get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.integrator import StreamingIntegrator
from skidkin_ros.core.odometry.interval import DEFAULT_INTERVAL, INTERVALS
from skidkin_ros.core.online import online_odometer
from skidkin_ros.core.online.adapt import PROBE_M, PROBE_RAD
from skidkin_ros.core.online.window import _stack
from skidkin_ros.errors import DataError
from skidkin_ros.sim.simulate import SimConfig, simulate, Simulation

__all__ = ['causal_fits', 'causal_poses', 'causal_floor', 'increment_parts']

PARTS = ('before', 'straddle', 'change', 'after')


def training(interval: str = DEFAULT_INTERVAL) -> HorizonOptions:
    """Return the calibrator's training segments under a sample-interval convention."""
    return HorizonOptions(interval=interval).train_segments()


def _ground_segments(wheels: WheelSamples, reference: PoseTrack, t0_ns: int, t1_ns: int,
                     interval: str = DEFAULT_INTERVAL):
    """Return one ground's reference track, its drive and its training segments, or None.

    The ground is [t0_ns, t1_ns) of the wheels and the reference.
    """
    keep = (wheels.t_ns >= t0_ns) & (wheels.t_ns < t1_ns)
    on = (reference.t_ns >= t0_ns) & (reference.t_ns < t1_ns)
    if on.sum() < 2 or not keep.any():
        return None
    track = PoseTrack(reference.t_ns[on], reference.x[on], reference.y[on], reference.yaw[on])
    drive = Drive('ground', WheelSamples(wheels.t_ns[keep], wheels.omega_l[keep],
                                         wheels.omega_r[keep]), track)
    try:
        return track, drive, usable_segments([drive], training(interval), 'training')
    except DataError:
        return None


def causal_fits(wheels: WheelSamples, reference: PoseTrack, geometry: Geometry, t0_ns: int,
                t1_ns: int, model: str = study.MODEL, interval: str = DEFAULT_INTERVAL
                ) -> list[tuple[int, dict, float]]:
    """Return the causal refits of one ground, [t0_ns, t1_ns): (time seen, values, path m).

    The ground's data are cut once into the calibrator's training segments; the segments cut
    on the data up to any instant are those of this cut that end by then (the cut runs from the
    start, each segment ends at a reference pose, and the unfinished last one is dropped), so
    the i-th fit uses the first i segments and is usable from its last end pose on. Only the
    calibrator's valid fits are returned; ``path m``: the ground's reference path at that pose.
    """
    cut = _ground_segments(wheels, reference, t0_ns, t1_ns, interval)
    if cut is None:
        return []
    track, drive, segments = cut
    path = track.path_length()
    fits = []
    needed = len(get_model(model).params) + 1
    for i in range(max(needed, 2), len(segments) + 1):
        part = segments.subset(np.arange(i))
        if int(part.t_b_ns[-1]) >= t1_ns:
            break
        try:
            fit = fit_model_iterated(model, geometry, part)
        except DataError:
            continue
        if fit.valid:
            t_seen = int(part.t_b_ns[-1])
            index = int(np.searchsorted(track.t_ns, t_seen))
            fits.append((t_seen, dict(fit.values), float(path[min(index, path.size - 1)])))
    return fits


def prior_fits(wheels: WheelSamples, reference: PoseTrack, geometry: Geometry, t0_ns: int,
               t1_ns: int, start: dict, noise, prior_sigma: float, model: str = study.MODEL,
               iterations: int = 3, probes: bool = True, interval: str = DEFAULT_INTERVAL
               ) -> list[tuple[int, dict, float]]:
    """Return the causal MAP refits of one ground: the same segments, with a prior.

    Each new segment refits all the ground's segments so far (Gauss-Newton, ``iterations``
    steps from the last refit), weighted like the online learner (the noise model's covariance
    of each segment plus the reference's noise at both ends), with ``start`` as the prior's mean
    and ``prior_sigma`` of each parameter's typical magnitude as its spread (the online learner's
    new-ground prior): usable from the first segment on, no forgetting. ``probes``: also refit
    every PROBE_M of path or PROBE_RAD of turning inside a segment, with the segment in progress
    (from the last segment's end to the current pose) as one more segment, as the online learner
    probes (:mod:`skidkin_ros.core.online.adapt`).
    """
    cut = _ground_segments(wheels, reference, t0_ns, t1_ns, interval)
    if cut is None:
        return []
    track, drive, segments = cut
    kin = get_model(model)
    scale = parameter_scales(kin, geometry)
    anchor = kin.vector(dict(start), geometry)
    prior = np.eye(anchor.size) / prior_sigma ** 2
    # inside the parameters' ranges, as the online learner keeps them
    lo = np.array([p.lower + (1e-6 * c if p.lower_open else 0.0)
                   for p, c in zip(kin.params, scale)])
    hi = np.array([p.upper - (1e-6 * c if p.upper_open else 0.0)
                   for p, c in zip(kin.params, scale)])
    ref = np.diag([2 * study.REF_SIGMA_M ** 2, 2 * study.REF_SIGMA_M ** 2,
                   2 * study.REF_SIGMA_RAD ** 2])
    path = track.path_length()
    rows = [segments.subset([j]) for j in range(len(segments))]
    k = anchor.copy()
    fits = []
    done, last = 0, (-np.inf, 0.0)
    for c in range(1, len(track)):
        t_c = int(track.t_ns[c])
        if t_c >= t1_ns:
            break
        ended = done
        while ended < len(segments) and int(segments.t_b_ns[ended]) <= t_c:
            ended += 1
        batch = rows[:ended]
        if ended == done:   # inside a segment: a probe every PROBE_M or PROBE_RAD
            if not probes or (path[c] - last[0] < PROBE_M
                              and abs(track.yaw[c] - last[1]) < PROBE_RAD):
                continue
            a = (0 if done == 0 else
                 int(np.searchsorted(track.t_ns, int(segments.t_b_ns[done - 1]))))
            if training(interval).too_still(path[c] - path[a], track.yaw[c] - track.yaw[a]):
                continue
            part = Drive('part', drive.wheels, PoseTrack(track.t_ns[[a, c]], track.x[[a, c]],
                                                         track.y[[a, c]], track.yaw[[a, c]]))
            partial = cut_segments([part], training(interval))
            if len(partial) == 0:
                continue
            batch = batch + [partial]
        done = ended
        last = (path[c], track.yaw[c])
        stacked = _stack(batch)
        for _ in range(iterations):
            values = kin.mapping(k)
            e = segment_errors(kin, k, geometry, stacked)
            sens = parameter_sensitivity(kin.name, values, geometry, stacked) * scale
            inverse = np.linalg.inv(segment_covariances(
                noise, segment_motion(kin.name, values, geometry, stacked)) + ref)
            info = np.einsum('nip,nij,njq->pq', sens, inverse, sens) + prior
            gradient = (np.einsum('nip,nij,nj->p', sens, inverse, e)
                        - prior @ ((k - anchor) / scale))
            k = np.clip(k + np.linalg.solve(info, gradient) * scale, lo, hi)
        fits.append((t_c, kin.mapping(k), float(path[c])))
    return fits


def causal_poses(wheels: WheelSamples, on_new: np.ndarray, starts: Sequence[BoundModel],
                 schedules: Sequence[Sequence[tuple[int, BoundModel]]], interval: str
                 ) -> np.ndarray:
    """Integrate the wheels with each ground's parameters in force, as they were known.

    ``on_new``: per wheel sample, on the new ground (the change's instant, known); ``starts``:
    each ground's parameters before its first fit; ``schedules``: per ground, (time seen, model)
    in time order. A model seen at t is used for the steps after the first wheel sample at or
    after t (the odometer integrates a step, then hears the reference pose it covers).
    """
    integrator = StreamingIntegrator(starts[0], None, interval)
    poses = np.empty((len(wheels), 3))
    current, nxt = 0, 0
    last_t = None
    for i, (t, left, right) in enumerate(zip(wheels.t_ns.tolist(), wheels.omega_l,
                                             wheels.omega_r)):
        if int(on_new[i]) != current:
            current, nxt = int(on_new[i]), 0
            integrator.set_source(starts[current])
        schedule = schedules[current]
        source = None
        while last_t is not None and nxt < len(schedule) and schedule[nxt][0] <= last_t:
            source = schedule[nxt][1]
            nxt += 1
        if source is not None:
            integrator.set_source(source)
        poses[i] = integrator.step(t, left, right).pose
        last_t = t
    return poses


def increment_parts(sim: Simulation, n: int, switch_ns: int, learn_m: float) -> dict:
    """Return the masks of the study's n increments: before, straddle, change, after."""
    truth = sim.pose_at(sim.wheels.t_ns)
    path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(truth[:, :2], axis=0).T))])
    start = np.arange(n)
    end = np.searchsorted(path, path[:n] + 2.0)
    switch = int(np.searchsorted(sim.wheels.t_ns, switch_ns))
    return {'before': end < switch, 'straddle': (start < switch) & (end >= switch),
            'change': (start >= switch) & (path[start] < path[switch] + learn_m),
            'after': path[start] >= path[switch] + learn_m}


def part_weights(true: tuple[np.ndarray, np.ndarray], parts: dict) -> dict:
    """Return each part's share of the true model's summed ε_t and ε_θ.

    An odometry's ratio r on a part of weight w adds (r - 1) w to its whole-drive ratio.
    """
    return {p: (float(true[0][m].sum() / true[0].sum()), float(true[1][m].sum() / true[1].sum()))
            for p, m in parts.items()}


def _true_models(sim: Simulation) -> tuple[BoundModel, BoundModel]:
    """Return the true model's two grounds, as lab.studies.online's _true_poses binds them."""
    model, geometry = get_model(study.MODEL), sim.config.geometry
    base, other = study.true_grounds()
    return model.bind(base, geometry), model.bind(other, geometry)


def causal_floor(seed: int, fixed: OdometryConfig, duration_s: float = 240.0,
                 learn_m: float = 10.0) -> dict:
    """Return ε_t, ε_θ (means) of online, the causal floors, the non-causal floor and the truth.

    Also, per odometry, the ratio to the true model on each part of the drive (PARTS), and the
    new ground's path to its first causal fit (m).
    """
    sim = simulate(SimConfig(duration_s=duration_s, seed=seed,
                             effects=study._effects('long stretches')))
    reference = study._reference(sim, np.random.default_rng(seed))
    config = OdometryConfig.from_flat({**fixed.values, 'online.enabled': True})
    odometer = online_odometer(config)
    noise, prior_sigma = odometer.learner.noise, odometer.learner.params.prior_sigma
    online = odometer.predict(sim.wheels, reference=reference)
    switch = sim.start_ns + int(0.5 * duration_s * 1e9)
    model, geometry = get_model(study.MODEL), sim.config.geometry
    mask = sim.trace.masks['terrain_regime']
    on_new = np.interp(sim.wheels.t_ns, sim.trace.t_ns, mask.astype(float)) > 0.5
    interval = fixed['interval']
    fits = [causal_fits(sim.wheels, reference, geometry, sim.start_ns, switch,
                        interval=interval),
            causal_fits(sim.wheels, reference, geometry, switch, sim.end_ns + 1,
                        interval=interval)]
    schedules = [[(t, model.bind(v, geometry)) for t, v, _ in f] for f in fits]
    file_values = {k: fixed[f'models.{study.MODEL}.{k}'] for k in model.param_names}
    file_model = model.bind(file_values, geometry)
    with_prior = prior_fits(sim.wheels, reference, geometry, switch, sim.end_ns + 1,
                            file_values, noise, prior_sigma, interval=interval)
    previous = schedules[0][-1][1] if schedules[0] else file_model
    true_models = _true_models(sim)
    # the last causal fit of a ground uses all its segments: the non-causal floor's fit
    whole = [s[-1][1] if s else file_model for s in schedules]
    poses = {
        'online': online.poses,
        'causal previous': causal_poses(sim.wheels, on_new, (file_model, previous), schedules,
                                        fixed['interval']),
        'causal true': causal_poses(sim.wheels, on_new, (file_model, true_models[1]),
                                    schedules, fixed['interval']),
        'file, causal true': causal_poses(sim.wheels, on_new, (file_model, true_models[1]),
                                          ([], schedules[1]), fixed['interval']),
        'file, causal prior': causal_poses(
            sim.wheels, on_new, (file_model, file_model),
            ([], [(t, model.bind(v, geometry)) for t, v, _ in with_prior]), fixed['interval']),
        'non-causal': study.ground_poses(sim, whole, fixed['interval']),
        'true': study._true_poses(sim, fixed['interval'])}
    scores = {name: study._scores(sim, p) for name, p in poses.items()}
    parts = increment_parts(sim, scores['true'][0].size, switch, learn_m)
    out = {'seed': seed, 'first_fit_m': fits[1][0][2] if fits[1] else float('inf'),
           'weights': part_weights(scores['true'], parts)}
    for name, (eps_t, eps_th) in scores.items():
        out[name] = (float(eps_t.mean()), float(eps_th.mean()))
        for part, m in parts.items():
            out[(name, part)] = (float(eps_t[m].mean() / scores['true'][0][m].mean()),
                                 float(eps_th[m].mean() / scores['true'][1][m].mean()))
    return out


HEADER = ('| seed | ε_t online / causal previous / causal true / file, causal true / file, '
          'causal prior / non-causal / true | ε_t ratios to true: the first six | ε_θ the same | '
          'ε_θ ratios to true | online / causal previous ε_t, ε_θ | on the parts before, '
          'straddle, change, after: online / true ε_t; ε_θ | causal previous / true | causal '
          'true / true | file, causal true / true | file, causal prior / true | first fit m |\n'
          + '|---' * 13 + '|')
ORDER = ('online', 'causal previous', 'causal true', 'file, causal true', 'file, causal prior',
         'non-causal', 'true')


def row(r: dict) -> str:
    """One drive as a markdown table row."""
    cells = [str(r['seed'])]
    for col in (0, 1):
        cells.append(' / '.join(f'{r[k][col]:.4f}' for k in ORDER))
        cells.append(', '.join(f'{r[k][col] / r["true"][col]:.2f}' for k in ORDER[:6]))
    o, c = r['online'], r['causal previous']
    cells.append(f'{o[0] / c[0]:.2f}, {o[1] / c[1]:.2f}')
    for name in ('online', 'causal previous', 'causal true', 'file, causal true',
                 'file, causal prior'):
        cells.append(', '.join(f'{r[(name, p)][0]:.2f}' for p in PARTS) + '; '
                     + ', '.join(f'{r[(name, p)][1]:.2f}' for p in PARTS))
    cells.append(f'{r["first_fit_m"]:.1f}')
    return '| ' + ' | '.join(cells) + ' |'


def summary(results: list[dict]) -> str:
    """Means and counts within 1.5x of the true model, per odometry."""
    lines = []
    for name in ORDER[:6]:
        for col, what in ((0, 'ε_t'), (1, 'ε_θ')):
            ratios = np.array([r[name][col] / r['true'][col] for r in results])
            lines.append(f'{name} {what}/true: {ratios.min():.2f}-{ratios.max():.2f}, mean '
                         f'{ratios.mean():.3f}, <= 1.5 on {(ratios <= 1.5).sum()} of '
                         f'{ratios.size}')
    return '\n'.join(lines)


def _one(args: tuple) -> dict:
    seed, fixed, learn_m = args
    return causal_floor(seed, fixed, learn_m=learn_m)


def main(argv: list[str] | None = None) -> int:
    """Print the causal floor of every seed."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[1, 2])
    parser.add_argument('--learn-m', type=float, default=10.0)
    parser.add_argument('--jobs', type=int, default=1)
    parser.add_argument('--interval', choices=INTERVALS,
                        help="the file's sample-interval convention (default: the study's)")
    args = parser.parse_args(argv)
    fixed = study.calibrated_file(interval=args.interval)
    print(HEADER, flush=True)
    work = [(seed, fixed, args.learn_m) for seed in args.seeds]
    results = []
    if args.jobs > 1:
        with ProcessPoolExecutor(args.jobs) as pool:
            for r in pool.map(_one, work):
                results.append(r)
                print(row(r), flush=True)
    else:
        for item in work:
            results.append(_one(item))
            print(row(results[-1]), flush=True)
    print('\n' + summary(results))
    return 0


if __name__ == '__main__':
    sys.exit(main())
