"""The reference's delay checked online by the offline lag rule (core/online/delay.py)."""

import math

import numpy as np
import pytest
from skidkin_ros.core.calibration.lag import lag_sigma, scan
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.online import online_odometer
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate

FILE = {'model': 'edd_asymmetric', 'robot': 'sim_husky',
        **{f'models.edd_asymmetric.{k}': v for k, v in DEFAULT_TRUE_PARAMS.items()},
        'models.edd_asymmetric.noise.calibrated': True, 'online.enabled': True,
        'online.delay_tolerance': 0.06}   # the check is off by default


def test_scan_finds_the_minimum_and_its_sigma():
    best, lags, curve = scan(lambda lag: (lag - 0.23) ** 2 + 1e-4, 0.6)
    assert best == pytest.approx(0.23)
    assert lags.min() >= -0.6 - 1e-9 and lags.max() <= 0.6 + 1e-9
    # cost_min / (count * a) with a = 1: sqrt(1e-4 / 100) = 1 ms, floored at half a step
    assert lag_sigma(lags, curve, 100) == pytest.approx(0.005)
    assert lag_sigma(lags, curve, 1) == math.inf
    flat = np.zeros_like(curve)
    assert lag_sigma(lags, flat, 100) == math.inf


def _drive(delay_s, seed=4, duration_s=60.0):
    sim = simulate(SimConfig(duration_s=duration_s, seed=seed))
    t = np.arange(sim.start_ns + 1_000_000_000, sim.end_ns - 1_000_000_000, 100_000_000)
    truth = sim.truth_at(t)
    rng = np.random.default_rng(seed)
    n = len(t)
    return sim, PoseTrack(t + int(round(delay_s * 1e9)), truth.x + rng.normal(0, 0.01, n),
                          truth.y + rng.normal(0, 0.01, n), truth.yaw + rng.normal(0, 0.003, n))


def _run(sim, reference, **online):
    warnings = []
    config = OdometryConfig.from_flat({**FILE, **{f'online.{k}': v for k, v in online.items()}})
    odometer = online_odometer(config, warn=lambda cause, msg, **k: warnings.append((cause, msg)))
    result = odometer.predict(sim.wheels, reference=reference)
    return odometer, result, warnings


def test_a_late_reference_is_taken_in_force_once_and_said():
    sim, reference = _drive(0.4)
    odometer, _, warnings = _run(sim, reference)
    summary = odometer.learner.summary()
    assert odometer.counters['online_delay_corrected'] == 1
    said = [msg for cause, msg in warnings if cause == 'reference_delay']
    assert len(said) == 1 and 'set online.time_offset: 0.' in said[0]
    # the offset in force, checked again after the correction: within the tolerance
    assert summary['measured_delay'] == pytest.approx(0.4, abs=0.1)
    assert summary['delay_check'] == 'ok'
    assert odometer.counters['online_reference_delay'] == 0
    # and it learns about as the right constant would: told, the user sets it
    told, _, _ = _run(sim, reference, time_offset=0.4)
    assert told.counters['online_delay_corrected'] == 0
    assert odometer.counters['online_segments'] >= 0.7 * told.counters['online_segments']


def test_without_delay_learn_learning_pauses_and_says_the_value_to_set():
    sim, reference = _drive(0.4)
    odometer, _, warnings = _run(sim, reference, delay_learn=0.0)
    summary = odometer.learner.summary()
    assert summary['measured_delay'] == pytest.approx(0.4, abs=0.1)
    assert summary['measured_delay.sigma'] < 0.05
    assert summary['delay_check'] == 'paused'
    assert odometer.learner.state(sim.wheels.t_ns[-1] - 1_500_000_000) == 'holding'
    assert odometer.counters['online_reference_delay'] > 0
    assert odometer.counters['online_delay_corrected'] == 0
    said = [msg for cause, msg in warnings if cause == 'reference_delay']
    assert len(said) == 1 and 'set online.time_offset: 0.' in said[0]
    # told, the user sets it: the check passes and learning goes on
    fixed, _, _ = _run(sim, reference, time_offset=round(summary['measured_delay'], 2),
                       delay_learn=0.0)
    assert fixed.counters['online_reference_delay'] == 0
    assert fixed.learner.summary()['delay_check'] == 'ok'
    assert fixed.counters['online_segments'] > odometer.counters['online_segments']


def test_an_early_reference_is_measured_negative():
    sim, reference = _drive(-0.3, seed=5)
    odometer, _, _ = _run(sim, reference, delay_learn=0.0)
    assert odometer.learner.summary()['measured_delay'] == pytest.approx(-0.3, abs=0.1)
    assert odometer.counters['online_reference_delay'] > 0


def test_a_right_offset_learns_bit_for_bit_as_unchecked():
    sim, reference = _drive(0.2, seed=6)
    checked, result, _ = _run(sim, reference, time_offset=0.2)
    unchecked, plain, _ = _run(sim, reference, time_offset=0.2, delay_tolerance=0.0)
    assert checked.learner.summary()['delay_check'] == 'ok'
    assert unchecked.learner.summary()['delay_check'] == 'off'
    assert checked.counters['online_segments'] >= 10
    assert np.array_equal(result.poses, plain.poses)
    assert np.array_equal(result.pose_covariances, plain.pose_covariances)


def test_delay_tolerance_zero_never_pauses():
    sim, reference = _drive(0.4)
    odometer, _, warnings = _run(sim, reference, delay_tolerance=0.0)
    assert odometer.counters['online_reference_delay'] == 0
    assert not [w for w in warnings if w[0] == 'reference_delay']
    assert odometer.counters['online_delay_corrected'] == 0
    summary = odometer.learner.summary()
    assert summary['delay_check'] == 'off' and math.isnan(summary['measured_delay'])
