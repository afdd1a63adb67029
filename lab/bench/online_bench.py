"""Cost of online calibration per wheel sample: 1 kHz wheels, a 10 Hz reference, vs today.

The node's work per wheel sample is the odometer's (:class:`Odometer.update`: stamp checks,
integration, covariance, the output); online calibration adds a list append per sample and, per
reference pose and per segment, the learner's work. Both odometers run the same simulated drive
(1 kHz wheel samples, ``edd_asymmetric`` with a calibrated noise, a ground change at half the
drive) in turns, each timed ``--repeats`` times; the best run of each is compared (the ratio is
measured in one run on one machine as process CPU time, never asserted). Run::

    python -m lab.bench.online_bench --seconds 60 --repeats 3

``--old CHECKOUT`` also times, in the same turns, the odometers with the covariance propagator
of another checkout (its ``skidkin_ros/core/odometry/propagation.py``, loaded beside this one
and given this checkout's ``ParameterUncertainty``: the parameter uncertainty's cost before and
after a change), for the file with a parameter
covariance and for the same file without one (the node's default), and prints the medians of
the paired ratios.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import pathlib
import sys
import time

import numpy as np
from skidkin_ros.core.odometry import odometer as odometer_module
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


def _old_propagator(checkout: str):
    """Return another checkout's PoseCovariancePropagator class, loaded under its own name."""
    path = pathlib.Path(checkout) / 'skidkin_ros' / 'core' / 'odometry' / 'propagation.py'
    spec = importlib.util.spec_from_file_location('_old_propagation', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.PoseCovariancePropagator


@contextlib.contextmanager
def _propagator_class(cls):
    """Build odometers with ``cls`` as their covariance propagator (None: this checkout's)."""
    saved = odometer_module.PoseCovariancePropagator
    if cls is not None:
        odometer_module.PoseCovariancePropagator = cls
    try:
        yield
    finally:
        odometer_module.PoseCovariancePropagator = saved


def _compare_old(args, sim, reference) -> None:
    """Time today/online x old/new propagator x file with/without a parameter covariance."""
    old = _old_propagator(args.old)
    no_cov = {k: v for k, v in FILE.items() if not k.endswith('parameter_covariance')}
    for label, flat in (('file with a parameter covariance', FILE),
                        ('file without one (the node default)', no_cov)):
        configs = {'off': OdometryConfig.from_flat(flat),
                   'on': OdometryConfig.from_flat({**flat, 'online.enabled': True})}
        runs = {key: [] for key in ('off old', 'off new', 'on old', 'on new')}
        for _ in range(args.repeats):
            for key in runs:
                state, code = key.split()
                with _propagator_class(old if code == 'old' else None):
                    runs[key].append(_run(configs[state], sim, reference)[0])
        cost = {key: float(np.median(v)) * 1e6 for key, v in runs.items()}
        ratio = {name: float(np.median(np.divide(runs[a], runs[b])))
                 for name, a, b in (('on/off old', 'on old', 'off old'),
                                    ('on/off new', 'on new', 'off new'),
                                    ('new/old off', 'off new', 'off old'),
                                    ('new/old on', 'on new', 'on old'))}
        print(f'{label}: median CPU us per wheel sample over {args.repeats} turns: '
              + ', '.join(f'{k} {v:.2f}' for k, v in cost.items()))
        print('  medians of the paired ratios: '
              + ', '.join(f'{k} {v:.3f}' for k, v in ratio.items()))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, default=60.0, help='drive length (s)')
    parser.add_argument('--repeats', type=int, default=3)
    parser.add_argument('--old', metavar='CHECKOUT',
                        help='also time the covariance propagator of this checkout (e.g. '
                             '/work/main), with and without a file parameter covariance')
    args = parser.parse_args(argv)
    effect = make_effect('terrain_regime', 0.25, mode='time', switch_frac=0.5, yaw=0.15)
    sim = simulate(SimConfig(duration_s=args.seconds, seed=1, wheel_rate_hz=1000.0,
                             effects=(effect,)))
    reference = sim.truth_at(np.arange(sim.start_ns, sim.end_ns, 100_000_000))
    if args.old:
        _compare_old(args, sim, reference)
        return 0
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
