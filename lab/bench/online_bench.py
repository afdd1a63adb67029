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

``--augmented`` times an augmented model instead (``edd_asymmetric`` + speed_slip +
ratio_yaw_slip, file without a parameter covariance, the drive with a speed-dependent slip and a
ground change): online off, and online on with this checkout's learner; with ``--old CHECKOUT``
also online on with that checkout's segment residuals and Jacobian
(``AugmentedCalibrator._residuals`` of its ``skidkin_ros/core/online/augmented.py``, loaded beside
this one), in the same turns. It prints the CPU per wheel sample, the learning's CPU per
reference pose (on minus off, over the poses) and how far the old and new learned values,
parameter covariances and poses are apart::

    python -m lab.bench.online_bench --augmented --seconds 60 --repeats 3 --old /work/main

``--augmented --residual``: the augmented model is ``edd_asymmetric`` + a residual model with a
rate term (its learning segments keep every wheel step: no 50 ms blocks); no ``--old`` (the
residual model was not learned online before).
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


AUGMENTED = {'model': 'augmented', 'augmented.base': 'edd_asymmetric',
             'augmented.extensions': 'speed_slip,ratio_yaw_slip',
             'augmented.speed_slip.k': 0.25, 'augmented.ratio_yaw_slip.k': 0.2,
             **{k: v for k, v in FILE.items()
                if k != 'model' and not k.endswith('parameter_covariance')}}


RESIDUAL = {**{k: v for k, v in AUGMENTED.items() if not k.startswith('augmented.')},
            'augmented.base': 'edd_asymmetric', 'augmented.extensions': 'residual_model',
            **{f'augmented.residual_model.{name}_{side}': sign * 3.0
               for name in ('v', 'w', 'dv', 'dw') for side, sign in (('lo', -1.0), ('hi', 1.0))},
            'augmented.residual_model.level': 3.0,
            'augmented.residual_model.vx_v_abs_v': -0.25 * 9.0,
            'augmented.residual_model.vx_dv_up': -0.05 * 3.0}


def _old_residuals(checkout: str):
    """Return another checkout's AugmentedCalibrator._residuals, its module loaded beside."""
    path = pathlib.Path(checkout) / 'skidkin_ros' / 'core' / 'online' / 'augmented.py'
    spec = importlib.util.spec_from_file_location('_old_online_augmented', path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module   # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module.AugmentedCalibrator._residuals


# CPU seconds and calls spent in the learner's segment residuals and Jacobian (_residuals).
_SPENT = [0.0, 0]


@contextlib.contextmanager
def _residuals(function):
    """Learn with ``function`` as the augmented learner's residuals (None: this checkout's).

    The residuals are timed into ``_SPENT`` (process CPU).
    """
    from skidkin_ros.core.online.augmented import AugmentedCalibrator
    saved = AugmentedCalibrator._residuals
    chosen = saved if function is None else function

    def timed(self, ground, segments):
        tic = time.process_time()
        try:
            return chosen(self, ground, segments)
        finally:
            _SPENT[0] += time.process_time() - tic
            _SPENT[1] += 1
    AugmentedCalibrator._residuals = timed
    try:
        yield
    finally:
        AugmentedCalibrator._residuals = saved


def _run_learned(config: OdometryConfig, sim, reference) -> tuple[float, dict, tuple]:
    """:func:`_run`, also returning the learned values, covariance and last pose."""
    odometer = online_odometer(config)
    odometer.reset()
    rows = list(zip(reference.t_ns.tolist(), reference.x.tolist(), reference.y.tolist(),
                    reference.yaw.tolist()))
    j, n = 0, len(rows)
    update, feed = odometer.update, odometer.reference_sample
    last = None
    tic = time.process_time()
    for t, left, right in zip(sim.wheels.t_ns.tolist(), sim.wheels.omega_l.tolist(),
                              sim.wheels.omega_r.tolist()):
        while j < n and rows[j][0] <= t:
            feed(*rows[j])
            j += 1
        last = update(t, left, right) or last
    seconds = time.process_time() - tic
    learner = odometer.learner
    learned = ((learner.k.copy(), learner.covariance.copy()) if learner is not None
               else (None, None))
    return seconds, dict(odometer.counters), learned + (np.array(last.pose),)


def _augmented(args) -> None:
    """Time an augmented model online: off, on (this checkout), on (--old's residuals)."""
    effects = (make_effect('speed_slip', 0.25),
               make_effect('terrain_regime', 0.25, mode='time', switch_frac=0.5, yaw=0.15))
    sim = simulate(SimConfig(duration_s=args.seconds, seed=1, wheel_rate_hz=1000.0,
                             effects=effects))
    reference = sim.truth_at(np.arange(sim.start_ns, sim.end_ns, 100_000_000))
    flat = RESIDUAL if args.residual else AUGMENTED
    configs = {'off': OdometryConfig.from_flat(flat),
               'on': OdometryConfig.from_flat({**flat, 'online.enabled': True})}
    old = _old_residuals(args.old) if args.old and not args.residual else None
    keys = ['off', 'on new'] + (['on old'] if old is not None else [])
    runs = {key: [] for key in keys}
    spent = {key: [] for key in keys}
    out = {}
    for _ in range(args.repeats):
        for key in keys:
            _SPENT[:] = [0.0, 0]
            with _residuals(old if key == 'on old' else None):
                seconds, counts, learned = _run_learned(configs[key.split()[0]], sim,
                                                        reference)
            runs[key].append(seconds)
            spent[key].append(tuple(_SPENT))
            out[key] = (counts, learned)
    samples, poses = len(sim.wheels), len(reference)
    cost = {key: float(np.median(v)) / samples * 1e6 for key, v in runs.items()}
    print(f'{samples} wheel samples at 1 kHz, {poses} reference poses at 10 Hz, '
          f'{out["on new"][0].get("online_segments", 0)} segments; medians of {args.repeats} '
          'turns, process CPU:')
    print('  us per wheel sample: ' + ', '.join(f'{k} {v:.2f}' for k, v in cost.items()))
    off = np.array(runs['off'])
    for key in keys[1:]:
        learning = (np.array(runs[key]) - off) / poses * 1e6
        ratio = float(np.median(np.array(runs[key]) / off))
        residual = np.array([t for t, _ in spent[key]])
        calls = spent[key][0][1]
        print(f'  {key}: online us per reference pose (on - off): '
              f'{float(np.median(learning)):.0f}; on/off {ratio:.3f}; segment residuals and '
              f'Jacobian: {calls} calls, {float(np.median(residual)) / calls * 1e6:.0f} us '
              f'per call, {float(np.median(residual)) / poses * 1e6:.0f} us per reference pose')
    if old is not None:
        new_on, old_on = np.array(runs['on new']), np.array(runs['on old'])
        residuals = [a[0] / b[0] for a, b in zip(spent['on new'], spent['on old'])]
        print('  medians of the paired ratios new/old: on '
              f'{float(np.median(new_on / old_on)):.3f}, on - off '
              f'{float(np.median((new_on - off) / (old_on - off))):.3f}, segment residuals '
              f'and Jacobian {float(np.median(residuals)):.3f}')
        (k_new, cov_new, pose_new), (k_old, cov_old, pose_old) = (out['on new'][1],
                                                                  out['on old'][1])
        values = np.max(np.abs(k_new - k_old) / np.abs(k_old))
        covariance = np.max(np.abs(cov_new - cov_old)) / np.max(np.abs(cov_old))
        print(f'  new vs old: values max rel diff {values:.2e}, covariance max rel diff '
              f'{covariance:.2e}, last pose diff {np.max(np.abs(pose_new - pose_old)):.2e} '
              f'(m, rad); counts equal: {out["on new"][0] == out["on old"][0]}')


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, default=60.0, help='drive length (s)')
    parser.add_argument('--repeats', type=int, default=3)
    parser.add_argument('--old', metavar='CHECKOUT',
                        help='also time the covariance propagator of this checkout (e.g. '
                             '/work/main), with and without a file parameter covariance')
    parser.add_argument('--augmented', action='store_true',
                        help='time an augmented model learning online (see above)')
    parser.add_argument('--residual', action='store_true',
                        help='with --augmented: a residual model with a rate term instead')
    parser.add_argument('--delay-check', action='store_true',
                        help="also time online with the reference's delay not checked "
                             '(online.delay_tolerance 0), in the same turns')
    args = parser.parse_args(argv)
    if args.augmented:
        _augmented(args)
        return 0
    effect = make_effect('terrain_regime', 0.25, mode='time', switch_frac=0.5, yaw=0.15)
    sim = simulate(SimConfig(duration_s=args.seconds, seed=1, wheel_rate_hz=1000.0,
                             effects=(effect,)))
    reference = sim.truth_at(np.arange(sim.start_ns, sim.end_ns, 100_000_000))
    if args.old:
        _compare_old(args, sim, reference)
        return 0
    today = OdometryConfig.from_flat(FILE)
    online = OdometryConfig.from_flat({**FILE, 'online.enabled': True})
    best = {'today': np.inf, 'online': np.inf, 'unchecked': np.inf}
    counters = {}
    ratios = []
    runs = [('today', today), ('online', online)]
    if args.delay_check:
        runs.append(('unchecked', OdometryConfig.from_flat(
            {**FILE, 'online.enabled': True, 'online.delay_tolerance': 0.0})))
    checks = []
    for _ in range(args.repeats):
        pair = {}
        for name, config in runs:
            cost, counts = _run(config, sim, reference)
            best[name] = min(best[name], cost)
            counters[name] = counts
            pair[name] = cost
        ratios.append(pair['online'] / pair['today'])
        if args.delay_check:
            checks.append(pair['online'] / pair['unchecked'])
    print(f'{len(sim.wheels)} wheel samples at 1 kHz, {len(reference)} reference poses at '
          f'10 Hz, best of {args.repeats}:')
    print(f'  today (online off): {best["today"] * 1e6:.2f} us per wheel sample')
    print(f'  online calibration: {best["online"] * 1e6:.2f} us per wheel sample '
          f'({counters["online"].get("online_segments", 0)} segments, '
          f'{counters["online"].get("online_change", 0)} change(s))')
    print(f'  ratio of the best runs: {best["online"] / best["today"]:.2f}; median of the '
          f'{len(ratios)} paired runs: {float(np.median(ratios)):.2f} (CPU time of this process)')
    if args.delay_check:
        print(f"  delay not checked: {best['unchecked'] * 1e6:.2f} us per wheel sample; "
              f"checked / not: best {best['online'] / best['unchecked']:.3f}, median of the "
              f'paired runs {float(np.median(checks)):.3f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
