"""Cost of online calibration per wheel sample: 1 kHz wheels, a 10 Hz reference, vs today.

The node's work per wheel sample is the odometer's (:class:`Odometer.update`: stamp checks,
integration, covariance, the output); online calibration adds a list append per sample and, per
reference pose and per segment, the learner's work. Both odometers run the same simulated drive
(1 kHz wheel samples, ``edd_asymmetric`` with a calibrated noise, a ground change at half the
drive) in turns, each timed ``--repeats`` times; the best run of each is compared (the ratio is
measured in one run on one machine as process CPU time, never asserted). Run::

    python -m lab.bench.online_bench --seconds 60 --repeats 3
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.online import online_odometer
from skidkin_ros.sim.effects import make_effect
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate

FILE = {'model': 'edd_asymmetric',
        **{f'models.edd_asymmetric.{k}': v for k, v in DEFAULT_TRUE_PARAMS.items()},
        'models.edd_asymmetric.noise.calibrated': True,
        'models.edd_asymmetric.noise.var_x_per_m': 1.2e-4,
        'models.edd_asymmetric.noise.var_yaw_per_rad': 2e-4,
        'models.edd_asymmetric.parameter_covariance': list(np.diag([1e-6] * 5).ravel())}


def _run(config: OdometryConfig, sim, reference) -> tuple[float, dict]:
    odometer = online_odometer(config)
    odometer.reset()
    wheels = sim.wheels
    rows = list(zip(reference.t_ns.tolist(), reference.x.tolist(), reference.y.tolist(),
                    reference.yaw.tolist()))
    j, n = 0, len(rows)
    update, feed = odometer.update, odometer.reference_sample
    tic = time.process_time()
    for t, left, right in zip(wheels.t_ns.tolist(), wheels.omega_l.tolist(),
                              wheels.omega_r.tolist()):
        while j < n and rows[j][0] <= t:
            feed(*rows[j])
            j += 1
        update(t, left, right)
    seconds = time.process_time() - tic
    return seconds / len(wheels), dict(odometer.counters)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, default=60.0, help='drive length (s)')
    parser.add_argument('--repeats', type=int, default=3)
    args = parser.parse_args(argv)
    effect = make_effect('terrain_regime', 0.25, mode='time', switch_frac=0.5, yaw=0.15)
    sim = simulate(SimConfig(duration_s=args.seconds, seed=1, wheel_rate_hz=1000.0,
                             effects=(effect,)))
    reference = sim.truth_at(np.arange(sim.start_ns, sim.end_ns, 100_000_000))
    today = OdometryConfig.from_flat(FILE)
    online = OdometryConfig.from_flat({**FILE, 'online.enabled': True})
    best = {'today': np.inf, 'online': np.inf}
    counters = {}
    ratios = []
    for _ in range(args.repeats):
        pair = {}
        for name, config in (('today', today), ('online', online)):
            cost, counts = _run(config, sim, reference)
            best[name] = min(best[name], cost)
            counters[name] = counts
            pair[name] = cost
        ratios.append(pair['online'] / pair['today'])
    print(f'{len(sim.wheels)} wheel samples at 1 kHz, {len(reference)} reference poses at '
          f'10 Hz, best of {args.repeats}:')
    print(f'  today (online off): {best["today"] * 1e6:.2f} us per wheel sample')
    print(f'  online calibration: {best["online"] * 1e6:.2f} us per wheel sample '
          f'({counters["online"].get("online_segments", 0)} segments, '
          f'{counters["online"].get("online_change", 0)} change(s))')
    print(f'  ratio of the best runs: {best["online"] / best["today"]:.2f}; median of the '
          f'{len(ratios)} paired runs: {float(np.median(ratios)):.2f} (CPU time of this process)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
