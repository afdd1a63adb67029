"""The reference's delay checked online: before (not checked) and after, side by side in one run.

Simulated drives of lab.studies.online (``long stretches``: a change of ground at half the
drive, and ``effect-free``), the 10 Hz reference stamped ``delay`` seconds late (negative:
early) while ``online.time_offset`` stays 0 (a user who does not know it). Three odometries on
the same wheel samples: ``before`` (``online.delay_tolerance`` 0: today's learner, nothing
checked), ``pause`` (``online.delay_learn`` 0: learning pauses while the measured delay is
off), ``after`` (the defaults: the measured delay taken in force) and ``fixed`` (the calibrated
file, no learning); ``set`` is the learner with time_offset set to the true delay (what the
warning says to do). Scores: eps_t (m), eps_th (rad), changes of ground detected
(``online_change``; long stretches: 1 is right) and, for ``after``, the time_offset in force at
the end and the corrections made. Run::

    python -m lab.bench.online_delay [--seeds 1 8 9] [--duration 120] [--tolerance 0.06]
        [--interval midpoint]

The file is calibrated under ``interval: midpoint`` (exact for the simulator's speeds, which are
sampled at the stamp); ``--interval ending`` runs the default convention, under which the wheels'
integrated motion leads the truth by half a wheel period and the measured delay reads that much
late (25 ms at 20 Hz).
"""

from __future__ import annotations

import argparse
import sys
import time

from lab.studies.online import _effects, _scores, calibrated_file, REF_SIGMA_M, REF_SIGMA_RAD
import numpy as np
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.core.online import online_odometer
from skidkin_ros.sim.simulate import SimConfig, simulate

DELAYS = (0.0, 0.1, 0.3, 0.5, -0.2)


def late_reference(sim, rng: np.random.Generator, delay_s: float) -> PoseTrack:
    """Return the study's 10 Hz reference of the truth, stamped delay_s late."""
    t = np.arange(sim.start_ns + 1_000_000_000, sim.end_ns - 1_000_000_000, 100_000_000)
    truth = sim.truth_at(t)
    n = len(t)
    return PoseTrack(t + int(round(delay_s * 1e9)), truth.x + rng.normal(0, REF_SIGMA_M, n),
                     truth.y + rng.normal(0, REF_SIGMA_M, n),
                     truth.yaw + rng.normal(0, REF_SIGMA_RAD, n))


def run(case: str, seed: int, delay_s: float, fixed: OdometryConfig, duration_s: float,
        tolerance: float | None = None) -> dict:
    sim = simulate(SimConfig(duration_s=duration_s, seed=seed, effects=_effects(case)))
    reference = late_reference(sim, np.random.default_rng(seed), delay_s)
    out = {}
    plain = Odometer.from_config(fixed).predict(sim.wheels)
    out['fixed'] = (*(float(v.mean()) for v in _scores(sim, plain.poses)), 0, 0, float('nan'))
    for name, extra in (('before', {'online.delay_tolerance': 0.0}),
                        ('pause', {'online.delay_learn': 0.0}), ('after', {}),
                        ('set', {'online.time_offset': delay_s})):
        if tolerance is not None and name != 'before':
            extra = {'online.delay_tolerance': tolerance, **extra}
        config = OdometryConfig.from_flat({**fixed.values, 'online.enabled': True, **extra})
        odometer = online_odometer(config)
        result = odometer.predict(sim.wheels, reference=reference)
        eps_t, eps_th = (float(v.mean()) for v in _scores(sim, result.poses))
        learner = odometer.learner
        out[name] = (eps_t, eps_th, learner.counters['online_change'],
                     learner.counters['online_reference_delay'],
                     learner.summary()['measured_delay'],
                     learner.counters['online_delay_corrected'])
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[1, 8, 9])
    parser.add_argument('--cases', nargs='+', default=['long stretches', 'effect-free'])
    parser.add_argument('--delays', type=float, nargs='+', default=list(DELAYS))
    parser.add_argument('--duration', type=float, default=120.0)
    parser.add_argument('--interval', default='midpoint', choices=('midpoint', 'ending'),
                        help='the sample-interval convention of the file: midpoint (exact for '
                        'the speeds of the simulator, sampled at the stamp; what calibrate '
                        'chooses on them) or ending (the wheels lead by half a wheel period)')
    parser.add_argument('--tolerance', type=float, default=0.06,
                        help='online.delay_tolerance (s) of pause, after and set (the check is '
                        'off by default in a file: 0)')
    args = parser.parse_args(argv)
    tic = time.perf_counter()
    fixed = calibrated_file(interval=args.interval)
    print(f'interval: {args.interval}')
    print('| case | seed | delay s | eps_t fixed | eps_t before / pause / after / set | '
          'eps_th before / pause / after / set | changes before / pause / after / set | '
          'corrected to s (times) |')
    print('|---|---|---|---|---|---|---|---|')
    for case in args.cases:
        for seed in args.seeds:
            for delay in args.delays:
                r = run(case, seed, delay, fixed, args.duration, args.tolerance)
                runs = [r[k] for k in ('before', 'pause', 'after', 'set')]
                a = r['after']
                print(f'| {case} | {seed} | {delay:+.1f} | {r["fixed"][0]:.3f} | '
                      + ' / '.join(f'{x[0]:.3f}' for x in runs) + ' | '
                      + ' / '.join(f'{x[1]:.3f}' for x in runs) + ' | '
                      + ' / '.join(f'{x[2]}' for x in runs) + ' | '
                      f'{a[4]:+.2f} ({a[5]}) |', flush=True)
    print(f'\n({time.perf_counter() - tic:.0f} s)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
