"""Quantised and misbehaving encoders: `wheel_signal` auto and position measure the same distance.

A real encoder reports whole counts: between two counts its position repeats while the wheel
turns. These tests drive a simulated quantised encoder through the odometer (the node's and
``skidkin predict``'s code) and check the distance against the true one.
"""

import math

import numpy as np
import pytest
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.core.odometry.wheels import POSITION_LIMIT_RAD, STALE_TRAVEL_RAD, WheelSignal

NS = 1_000_000_000
T0 = 1_000 * NS
RADIUS = 0.1651


def _encoder_drive(rate_hz, counts, distance_m=0.5, speed_m_s=0.5, velocity_noise=0.0,
                   seed=0):
    """Yield (t_ns, omega, position) of a straight drive: a ramp up, cruise and ramp down.

    The position is the encoder's (whole counts), the velocity the true wheel speed (plus
    noise): what a driver that differences nothing publishes.
    """
    rng = np.random.default_rng(seed)
    quantum = 2 * math.pi / counts
    omega_max = speed_m_s / RADIUS
    ramp_s = 0.2
    total_rad = distance_m / RADIUS
    cruise_s = total_rad / omega_max - ramp_s
    duration = 2 * ramp_s + cruise_s + 0.5
    n = int(duration * rate_hz)
    t = np.arange(n) / rate_hz
    omega = omega_max * np.clip(np.minimum(t / ramp_s, (2 * ramp_s + cruise_s - t) / ramp_s),
                                0.0, 1.0)
    theta = np.concatenate([[0.0], np.cumsum(0.5 * (omega[1:] + omega[:-1]) / rate_hz)])
    position = np.floor(theta / quantum + 1e-9) * quantum + 1.234   # an arbitrary start count
    noisy = omega + velocity_noise * rng.standard_normal(n)
    return [(T0 + int(round(ti * NS)), float(w), float(p))
            for ti, w, p in zip(t, noisy, position)], theta[-1] * RADIUS


def _distance(signal, drive):
    odometer = Odometer.from_config(OdometryConfig.from_flat({'wheel_signal': signal}))
    for t_ns, omega, position in drive:
        odometer.joint_sample(t_ns, omega, omega, t_ns, ((position,), (position,)))
    x, y, _ = odometer.pose
    return math.hypot(x, y)


@pytest.mark.parametrize('rate_hz, counts', [
    (1000, 4096), (100, 1024), (50, 100),          # the cases that fell (+67 %, +18 %, +68 %)
    (1000, 100), (1000, 360), (1000, 1024), (100, 100), (200, 2048), (50, 16384), (20, 360),
])
def test_auto_measures_the_distance_as_position_does_on_a_quantised_encoder(rate_hz, counts):
    drive, true_m = _encoder_drive(rate_hz, counts)
    quantum_m = 2 * math.pi / counts * RADIUS
    position = _distance('position', drive)
    auto = _distance('auto', drive)
    assert abs(position - true_m) <= quantum_m + 1e-9
    # auto may lose at most the count it takes over from the velocities (one quantum)
    assert abs(auto - position) <= quantum_m + 1e-9, (auto, position, true_m)
    assert abs(auto - true_m) <= 2 * quantum_m + 1e-9


def test_auto_ignores_velocity_noise_once_the_positions_count():
    drive, true_m = _encoder_drive(100, 1024, velocity_noise=0.5, seed=3)
    assert abs(_distance('auto', drive) - true_m) <= 0.005   # 1 %, the velocity-measured start


def test_auto_takes_over_from_the_velocities_without_counting_a_count_twice():
    signal = WheelSignal('auto', 50.0)
    q = 0.1
    # 0.5 rad/s, positions in steps of 0.1 rad sampled every 0.1 s: a count every other sample
    speeds = []
    for k in range(20):
        position = math.floor(0.05 * k / q + 1e-9) * q
        taken = signal.take(T0 + k * NS // 10, 0.5, 0.5, ((position,), (position,)))
        speeds.append(taken.speeds[0])
    travel = sum(s * 0.1 for s in speeds[1:])
    assert travel == pytest.approx(0.9, abs=q)        # 19 intervals at 0.5 rad/s: 0.95 rad
    assert signal.in_use == 'position'
    # the repeated positions are zero travel under position use, not the velocity
    assert speeds[-1] in (0.0, pytest.approx(1.0))


def test_frozen_positions_are_warned_under_position_and_left_by_auto():
    warned = {}
    for mode in ('position', 'auto'):
        causes = []
        odometer = Odometer.from_config(
            OdometryConfig.from_flat({'wheel_signal': mode}),
            warn=lambda cause, message, error=False, c=causes: c.append((cause, message)))
        # a good start (the positions count), then the driver's positions stick at 0.3 rad
        # while the velocities say 2 rad/s for 2 s
        for k in range(120):
            t_ns = T0 + k * 20_000_000
            position = min(0.04 * k, 0.3)
            odometer.joint_sample(t_ns, 2.0, 2.0, t_ns, ((position,), (position,)))
        x = float(odometer.pose[0])
        warned[mode] = (x, [c for c, _ in causes], causes)
    x_position, causes_position, messages = warned['position']
    assert causes_position == ['stale_position']    # said once, not per sample
    assert 'look frozen' in messages[0][1] and 'quarter turn' in messages[0][1]
    assert x_position == pytest.approx(0.3 * RADIUS, abs=1e-9)   # position keeps its choice
    x_auto, causes_auto, messages = warned['auto']
    assert causes_auto == ['stale_position'] and 'integrates the velocities' in messages[0][1]
    # auto lost at most the quarter turn it took to see the freeze, then went on the velocities
    true_x = 2.0 * RADIUS * 119 * 0.02
    assert true_x - STALE_TRAVEL_RAD * RADIUS - 0.05 <= x_auto <= true_x


def test_a_robot_at_rest_with_still_positions_is_not_called_frozen():
    signal = WheelSignal('position', 50.0)
    for k in range(2000):   # 200 s at rest; the velocity jitters around zero
        taken = signal.take(T0 + k * NS // 10, 0.01 * (-1) ** k, 0.0, ((5.0,), (5.0,)))
        assert taken.warning is None and taken.speeds == (0.0, 0.0) or k == 0


@pytest.mark.parametrize('huge', [1e16, -1e16, 2 * POSITION_LIMIT_RAD])
def test_positions_beyond_float_resolution_are_refused_not_read_as_zero_travel(huge):
    signal = WheelSignal('position', 50.0)
    signal.take(T0, 1.0, 1.0, ((0.0,), (0.0,)))
    taken = signal.take(T0 + NS // 10, 1.0, 1.0, ((huge,), (0.1,)))
    assert taken.speeds is None and taken.cause == 'position_range'
    assert 'no longer resolves' in taken.detail
    auto = WheelSignal('auto', 50.0)
    auto.take(T0, 1.0, 1.0, ((huge,), (huge,)))
    assert auto.take(T0 + NS // 10, 1.0, 1.0, ((huge + 2.0,), (huge,))).speeds == (1.0, 1.0)
    assert auto.in_use == 'velocity'
    # the limit is where neighbouring floats are 1e-6 rad apart
    assert np.spacing(POSITION_LIMIT_RAD) == pytest.approx(1e-6, rel=1.0)


@pytest.mark.parametrize('signal', ['auto', 'position'])
def test_a_coarse_encoder_at_1khz_reads_alike_in_the_bag_reader_and_the_odometer(
        tmp_path, signal):
    # 100 counts per turn at 1 kHz: one count in 1 ms reads 63 rad/s, a jump of the speed far
    # beyond max_wheel_acceleration; it is a count, not a glitch (the distance was 0 m)
    from skidkin_ros.adapters.bag_reader import open_recording
    from skidkin_ros.adapters.bag_writer import BagWriter
    drive, true_m = _encoder_drive(1000, 100)
    names = ['left_wheel', 'right_wheel']
    with BagWriter(tmp_path / 'bag') as writer:
        for t_ns, omega, position in drive:
            writer.write_joint_state('/joint_states', t_ns, names, [omega, omega],
                                     positions=[position, position])
    config = OdometryConfig.from_flat({'wheel_signal': signal})
    with open_recording(tmp_path / 'bag') as rec:    # what skidkin predict reads
        wheels = rec.read_wheels(wheel_signal=signal, left_joints=['left_wheel'],
                                 right_joints=['right_wheel'])
        notes = list(rec.notes)
    assert not any('jumped faster' in note for note in notes)
    offline = Odometer.from_config(config).predict(wheels, jumps_dropped=True)
    live = Odometer.from_config(config)
    for t_ns, omega, position in drive:
        live.joint_sample(t_ns, omega, omega, t_ns, ((position,), (position,)))
    assert live.counters['wheel_jump'] == 0
    assert np.array_equal(offline.poses[-1], live.pose)      # bit for bit
    assert abs(float(live.pose[0]) - true_m) <= 2 * math.pi / 100 * RADIUS
