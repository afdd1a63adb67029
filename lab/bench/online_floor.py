"""Is the true model a fair yardstick for the long stretches? The calibrated floor beside it.

The online study (lab.studies.online) scores the online odometry against the **true** model:
the simulator's parameters of the ground under the robot, switched at the exact instant of the
change. No calibrated odometry reaches it: the calibrator's own fit on effect-free drives (the
fixed file) is 1.07-1.11x it. This bench computes, for each long-stretch drive, two floors that
a calibrated odometry could reach at best, knowing the change's instant (non-causal):

* **calibrated, exact**: the offline calibrator (:func:`fit_model_iterated`, the study's
  training segments) fitted on each ground's whole stretch of the drive with the exact truth;
* **calibrated, reference**: the same on the study's reference (10 Hz, 1 cm / 0.003 rad of
  white noise: the data the online learner has), each ground fitted on its whole stretch.

It prints ε_t and ε_θ of the online odometry, of both floors and of the true model, and the
ratios online / true (the goal's) and online / calibrated-on-the-reference. Run::

    python -m lab.bench.online_floor --seeds 1 2 8 9
"""

from __future__ import annotations

import argparse
import sys

from lab.studies import online as study
import numpy as np

from skidkin_ros.core.calibration.segments import HorizonOptions, usable_segments
from skidkin_ros.core.calibration.weighting import fit_model_iterated
from skidkin_ros.core.drive import Drive, PoseTrack, WheelSamples
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.online import online_odometer
from skidkin_ros.sim.simulate import SimConfig, simulate


def _fit(sim, track: PoseTrack, t0: int, t1: int):
    """Fit the study's model on the wheels and the track between t0 and t1 (wheel time)."""
    w = sim.wheels
    keep = (w.t_ns >= t0) & (w.t_ns < t1)
    on = (track.t_ns >= t0) & (track.t_ns < t1)
    drive = Drive('part', WheelSamples(w.t_ns[keep], w.omega_l[keep], w.omega_r[keep]),
                  PoseTrack(track.t_ns[on], track.x[on], track.y[on], track.yaw[on]))
    segments = usable_segments([drive], HorizonOptions().train_segments(), 'training')
    fit = fit_model_iterated(study.MODEL, sim.config.geometry, segments)
    return get_model(study.MODEL).bind(fit.values, sim.config.geometry)


def floor(seed: int, fixed: OdometryConfig, duration_s: float = 240.0) -> dict:
    """Return ε_t, ε_θ (means) of online, both floors and the truth on one long-stretch drive."""
    sim = simulate(SimConfig(duration_s=duration_s, seed=seed,
                             effects=study._effects('long stretches')))
    reference = study._reference(sim, np.random.default_rng(seed))
    config = OdometryConfig.from_flat({**fixed.values, 'online.enabled': True})
    online = online_odometer(config).predict(sim.wheels, reference=reference)
    switch = sim.start_ns + int(0.5 * duration_s * 1e9)
    exact = PoseTrack(sim.truth.t_ns, sim.truth.poses[:, 0], sim.truth.poses[:, 1],
                      sim.truth.poses[:, 2])
    poses = {'online': online.poses, 'true': study._true_poses(sim, fixed['interval'])}
    for name, track in (('exact', exact), ('reference', reference)):
        sources = (_fit(sim, track, sim.start_ns, switch), _fit(sim, track, switch, sim.end_ns))
        poses[name] = study.ground_poses(sim, sources, fixed['interval'])
    out = {'seed': seed}
    for name, p in poses.items():
        eps_t, eps_th = study._scores(sim, p)
        out[name] = (float(eps_t.mean()), float(eps_th.mean()))
    return out


def main(argv: list[str] | None = None) -> int:
    """Print the floors of every seed."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[1, 2])
    args = parser.parse_args(argv)
    fixed = study.calibrated_file()
    print('| seed | ε_t online / true / calibrated exact / calibrated reference | ε_θ the same '
          '| online/true ε_t, ε_θ | calibrated reference/true ε_t, ε_θ | online/calibrated '
          'reference ε_t, ε_θ |\n' + '|---' * 6 + '|')
    for seed in args.seeds:
        r = floor(seed, fixed)
        o, t, e, c = r['online'], r['true'], r['exact'], r['reference']
        print(f'| {seed} | {o[0]:.4f} / {t[0]:.4f} / {e[0]:.4f} / {c[0]:.4f} | '
              f'{o[1]:.4f} / {t[1]:.4f} / {e[1]:.4f} / {c[1]:.4f} | {o[0] / t[0]:.2f}, '
              f'{o[1] / t[1]:.2f} | {c[0] / t[0]:.2f}, {c[1] / t[1]:.2f} | {o[0] / c[0]:.2f}, '
              f'{o[1] / c[1]:.2f} |', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
