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
ground change): online off, then on. With ``--old CHECKOUT`` each turn also runs this file in a
child process on that checkout's code (``PYTHONPATH=CHECKOUT``: every module old, the shared
kinematics included), off then on, so old and new alternate in one run; each side's ratios
come from its own process. It prints the CPU per wheel sample, the learning's CPU per reference
pose (on minus off, over the poses), the segment residuals' share, and how far the old and new
learned values, parameter covariances and poses are apart::

    python -m lab.bench.online_bench --augmented --seconds 60 --repeats 3 --old OLD_CHECKOUT

``--split``: the cost with the node's default file (no parameter covariance) split into the
parameter uncertainty it publishes and the learning, in the same turns::

    python -m lab.bench.online_bench --split --seconds 60 --repeats 3

``--augmented --residual``: the augmented model is ``edd_asymmetric`` + a residual model with a
rate term (its learning segments keep every wheel step, as pairs: no 50 ms blocks)::

    python -m lab.bench.online_bench --augmented --residual --seconds 60 --repeats 3 \
        --old OLD_CHECKOUT
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import os
import pathlib
import subprocess
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
    published = []   # every 100th published pose covariance (its upper triangle)
    tic = time.process_time()
    for i, (t, left, right) in enumerate(zip(sim.wheels.t_ns.tolist(),
                                             sim.wheels.omega_l.tolist(),
                                             sim.wheels.omega_r.tolist())):
        while j < n and rows[j][0] <= t:
            feed(*rows[j])
            j += 1
        last = update(t, left, right) or last
        if i % 100 == 99:
            published.append(last.pose_covariance)
    seconds = time.process_time() - tic
    learner = odometer.learner
    learned = ((learner.k.copy(), learner.covariance.copy()) if learner is not None
               else (None, None))
    upper = np.array(published)[:, [0, 1, 5, 7, 11, 35]]
    return seconds, dict(odometer.counters), learned + (np.array(last.pose), upper)


def _augmented_turn(args) -> dict:
    """One turn of ``--augmented``: online off, then on, in this process (JSON-ready numbers)."""
    effects = (make_effect('speed_slip', 0.25),
               make_effect('terrain_regime', 0.25, mode='time', switch_frac=0.5, yaw=0.15))
    sim = simulate(SimConfig(duration_s=args.seconds, seed=1, wheel_rate_hz=1000.0,
                             effects=effects))
    reference = sim.truth_at(np.arange(sim.start_ns, sim.end_ns, 100_000_000))
    flat = RESIDUAL if args.residual else AUGMENTED
    out = {'samples': len(sim.wheels), 'poses': len(reference)}
    for key in ('off', 'on'):
        config = OdometryConfig.from_flat({**flat, 'online.enabled': key == 'on'})
        _SPENT[:] = [0.0, 0]
        with _residuals(None):
            seconds, counts, (k, covariance, pose, published) = _run_learned(config, sim,
                                                                             reference)
        out[key] = {'cpu_s': seconds, 'counts': counts, 'residuals': list(_SPENT),
                    'k': None if k is None else k.tolist(),
                    'covariance': None if covariance is None else covariance.tolist(),
                    'pose': pose.tolist(), 'published': published.tolist()}
    return out


def _old_turn(args) -> dict:
    """One turn of ``--augmented`` run by this file in a child process on ``--old``'s code."""
    command = [sys.executable, str(pathlib.Path(__file__).resolve()), '--augmented', '--emit',
               '--seconds', str(args.seconds)] + (['--residual'] if args.residual else [])
    env = {**os.environ, 'PYTHONPATH': str(pathlib.Path(args.old).resolve())}
    done = subprocess.run(command, env=env, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def _augmented(args) -> None:
    """Time an augmented model online: off and on, this checkout's code and ``--old``'s."""
    if args.emit:
        print(json.dumps(_augmented_turn(args)))
        return
    turns = {'new': [], 'old': []}
    for _ in range(args.repeats):
        turns['new'].append(_augmented_turn(args))
        if args.old:
            turns['old'].append(_old_turn(args))
    first = turns['new'][0]
    samples, poses = first['samples'], first['poses']
    print(f'{samples} wheel samples at 1 kHz, {poses} reference poses at 10 Hz, '
          f'{first["on"]["counts"].get("online_segments", 0)} segments; medians of '
          f'{args.repeats} turns, process CPU'
          + (f' (old: {args.old}, in a child process):' if args.old else ':'))
    for code, runs in turns.items():
        if not runs:
            continue
        off = np.array([run['off']['cpu_s'] for run in runs])
        on = np.array([run['on']['cpu_s'] for run in runs])
        spent = np.array([run['on']['residuals'][0] for run in runs])
        calls = runs[0]['on']['residuals'][1]
        print(f'  {code}: us per wheel sample off {float(np.median(off)) / samples * 1e6:.2f}, '
              f'on {float(np.median(on)) / samples * 1e6:.2f}; on/off (median of paired) '
              f'{float(np.median(on / off)):.3f}; online us per reference pose (on - off) '
              f'{float(np.median(on - off)) / poses * 1e6:.0f}; segment residuals and '
              f'Jacobian: {calls} calls, {float(np.median(spent)) / max(calls, 1) * 1e6:.0f} us '
              f'per call, {float(np.median(spent)) / poses * 1e6:.0f} us per reference pose')
    if args.old:
        new_on = np.array([run['on']['cpu_s'] for run in turns['new']])
        old_on = np.array([run['on']['cpu_s'] for run in turns['old']])
        new_off = np.array([run['off']['cpu_s'] for run in turns['new']])
        old_off = np.array([run['off']['cpu_s'] for run in turns['old']])
        print('  medians of the paired ratios new/old: on '
              f'{float(np.median(new_on / old_on)):.3f}, off '
              f'{float(np.median(new_off / old_off)):.3f}, on - off '
              f'{float(np.median((new_on - new_off) / (old_on - old_off))):.3f}')
        new, old = turns['new'][-1]['on'], turns['old'][-1]['on']
        k_new, k_old = np.array(new['k']), np.array(old['k'])
        cov_new, cov_old = np.array(new['covariance']), np.array(old['covariance'])
        values = np.max(np.abs(k_new - k_old) / np.abs(k_old))
        covariance = np.max(np.abs(cov_new - cov_old)) / np.max(np.abs(cov_old))
        pose = np.max(np.abs(np.array(new['pose']) - np.array(old['pose'])))
        pub_new, pub_old = np.array(new['published']), np.array(old['published'])
        published = np.max(np.abs(pub_new - pub_old) / np.abs(pub_old).max(axis=1)[:, None])
        print(f'  new vs old: values max rel diff {values:.2e}, parameter covariance max rel '
              f'diff {covariance:.2e}, last pose diff {pose:.2e} (m, rad), published pose '
              f'covariance (every 100th sample) max diff {published:.2e} of its largest '
              f'entry; counts equal: {new["counts"] == old["counts"]}')


def _split(args, sim, reference) -> None:
    """Split online's cost with the node's default file (no parameter covariance) by part.

    In the same turns: online off; on; on publishing no parameter uncertainty (the learner
    learns, the propagator is given none); on with a learner that is fed no wheel step (it
    learns nothing: what remains is the prior's parameter uncertainty, carried per sample).
    """
    from skidkin_ros.core.online.calibrator import OnlineCalibrator
    propagator = odometer_module.PoseCovariancePropagator
    flat = {k: v for k, v in FILE.items() if not k.endswith('parameter_covariance')}
    off = OdometryConfig.from_flat(flat)
    on = OdometryConfig.from_flat({**flat, 'online.enabled': True})
    real_set, real_step = propagator.set_parameters, OnlineCalibrator.wheel_step
    variants = {
        'off': (off, real_set, real_step),
        'on': (on, real_set, real_step),
        'on, no parameter uncertainty published': (
            on, lambda self, parameters: real_set(self, None), real_step),
        'on, learner fed no wheel step': (
            on, real_set, lambda self, t1_ns, wheels, twist: False)}
    runs = {name: [] for name in variants}
    for _ in range(args.repeats):
        for name, (config, set_parameters, wheel_step) in variants.items():
            propagator.set_parameters, OnlineCalibrator.wheel_step = set_parameters, wheel_step
            try:
                runs[name].append(_run(config, sim, reference)[0])
            finally:
                propagator.set_parameters, OnlineCalibrator.wheel_step = real_set, real_step
    base = np.array(runs['off'])
    print(f'the node default file (no parameter covariance), {len(sim.wheels)} wheel samples at '
          f'1 kHz; medians of {args.repeats} turns, process CPU:')
    for name, values in runs.items():
        values = np.array(values)
        print(f'  {name}: {float(np.median(values)) * 1e6:.2f} us per wheel sample, '
              f'/off {float(np.median(values / base)):.3f}')


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
    parser.add_argument('--emit', action='store_true', help=argparse.SUPPRESS)
    parser.add_argument('--split', action='store_true',
                        help="split online's cost with the node's default file by part")
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
    if args.split:
        _split(args, sim, reference)
        return 0
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
