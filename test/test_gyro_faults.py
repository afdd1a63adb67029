"""A gyro that lies: its clock steps back, it is mounted the other way round, or in deg/s.

The odometer (the node's and ``skidkin predict``'s code) must never be locked out by a
restarted IMU driver, and never trust a gyro that contradicts the wheels beyond any skid.
"""

import collections

import numpy as np
import pytest
from skidkin_ros.core.drive import ImuSamples, WheelSamples
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.gyro import GyroBuffer, GyroParams, GyroStatus
from skidkin_ros.core.odometry.noise import NoiseModel
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.core.odometry.propagation import PoseCovariancePropagator

NS = 1_000_000_000
HOUR = 3600 * NS
GEOMETRY = Geometry(0.1651, 0.555)
MODEL_RATE = 0.1651 * 2.0 / 0.555      # ideal_dd yaw rate of wheels at 4 and 6 rad/s


def _odometer(mode, warnings=None, **imu):
    model = get_model('ideal_dd').bind({}, GEOMETRY)
    noise = NoiseModel(1e-3, 1e-3, 1e-4, 1e-3)

    def warn(cause, message, error=False):
        if warnings is not None:
            warnings.append((cause, message, error))
    return Odometer(model, covariance=PoseCovariancePropagator(noise, [1] * 6, [1] * 6),
                    imu=GyroParams(mode=mode, **imu), wheel_radius_m=GEOMETRY.wheel_radius,
                    warn=warn)


def _drive(seconds=20.0, rate_hz=20, omega=(4.0, 6.0)):
    t = (np.arange(int(seconds * rate_hz)) * (NS // rate_hz)).astype(np.int64) + NS
    return WheelSamples(t, np.full(t.size, omega[0]), np.full(t.size, omega[1]))


def _gyro(wheels, rate, hz=100):
    t = np.arange(int(wheels.t_ns[0]) - NS, int(wheels.t_ns[-1]) + NS, NS // hz)
    return ImuSamples(t.astype(np.int64), np.full(t.size, rate, dtype=float))


# ---------------------------------------------------------------- the gyro clock steps back
def test_a_gyro_clock_that_steps_back_is_followed_after_three_samples_not_locked_out():
    buffer = GyroBuffer(GyroParams(mode='fuse'))
    for k in range(10):
        assert buffer.add(HOUR + k * 10_000_000, 0.1) is GyroStatus.ACCEPTED
    # the IMU driver restarts: its clock is an hour behind; one stamp alone is refused
    assert buffer.add(k * 10_000_000, 0.2) is GyroStatus.OLDER
    assert buffer.add(HOUR + 100_000_000, 0.1) is GyroStatus.ACCEPTED   # the old clock goes on
    statuses = [buffer.add(NS + j * 10_000_000, 0.2) for j in range(4)]
    assert statuses == [GyroStatus.OLDER, GyroStatus.OLDER, GyroStatus.CLOCK_RESET,
                        GyroStatus.ACCEPTED]
    assert buffer.newest_ns == NS + 30_000_000
    assert buffer.stepped_back_s == pytest.approx(3600 + 0.1 - 1.02)
    # a small step back (under max_stamp_step_back) stays an older stamp, however many
    for j in range(5):
        assert buffer.add(NS + 30_000_000 - 2 * NS // 10 + j, 0.2) is GyroStatus.OLDER


def _feed(odometer, wheel_t, gyro_t, rate, now=2 * HOUR):
    """Hand wheel and gyro samples to the odometer in arrival order (arrival = list order)."""
    events = [(i / len(wheel_t), 'wheel', t) for i, t in enumerate(wheel_t)]
    events += [(i / len(gyro_t), 'gyro', t) for i, t in enumerate(gyro_t)]
    for _, kind, t in sorted(events):
        if kind == 'gyro':
            odometer.imu_sample(t, rate, now)
        else:
            odometer.joint_sample(t, 4.0, 6.0, now)


def test_the_gyro_is_used_again_when_the_imu_driver_restarts_after_the_wheel_driver():
    # Both drivers restart on a clock an hour behind, the wheels' first (the odometer resets),
    # then the IMU's a second later: the gyro was locked out for the hour.
    warnings = []
    odometer = _odometer('fuse', warnings)
    rate = 0.6 * MODEL_RATE
    ms10, ms50 = 10_000_000, 50_000_000
    _feed(odometer, [HOUR + k * ms50 for k in range(100)],              # 5 s on the old clock
          [HOUR - NS + k * ms10 for k in range(600)], rate)
    _feed(odometer, [10 * NS + k * ms50 for k in range(20)],            # the wheels restart
          [HOUR + 5 * NS + k * ms10 for k in range(100)], rate)          # the IMU not yet
    covered_before = odometer.counters['imu_interval_covered']
    _feed(odometer, [11 * NS + k * ms50 for k in range(200)],           # the IMU restarts too
          [11 * NS - ms50 + k * ms10 for k in range(1010)], rate)
    counts = odometer.counters
    assert counts['stamp_reset'] == 1 and counts['imu_clock_reset'] == 1
    assert any(cause == 'imu_clock_reset' and 'gyro clock stepped back by' in message
               for cause, message, _ in warnings)
    # after the restart the gyro covers the wheel intervals again (it was locked out)
    assert counts['imu_interval_covered'] - covered_before >= 195
    assert counts['imu_older'] == 2   # the two samples before the step back was confirmed
    assert odometer.gyro.last.yaw_from_gyro


def test_a_gyro_clock_step_back_is_the_same_in_predict():
    # offline, the recorded gyro goes through the same buffer: a stepped-back clock is followed
    odometer = _odometer('fuse')
    buffer = odometer.gyro.buffer
    for k in range(5):
        buffer.add(HOUR + k * 10_000_000, 0.0)
    wheels = _drive(seconds=5.0)
    pred = odometer.predict(wheels, imu=_gyro(wheels, 0.6 * MODEL_RATE))
    assert pred.poses[-1, 2] == pytest.approx(0.6 * MODEL_RATE * 4.95, rel=1e-6)


# ---------------------------------------------------------------- a gyro that contradicts
@pytest.mark.parametrize('mode', ['fuse', 'adapt'])
@pytest.mark.parametrize('factor, hint', [(-0.6, 'upside down'), (-1.0, 'upside down'),
                                          (0.6 * 57.29577951308232, 'deg/s')])
def test_a_gyro_that_contradicts_the_wheels_is_not_used_and_said_so(mode, factor, hint):
    warnings = []
    odometer = _odometer(mode, warnings)
    wheels = _drive()
    pred = odometer.predict(wheels, imu=_gyro(wheels, factor * MODEL_RATE))
    model_turn = MODEL_RATE * 19.95
    # at most the first check window (0.3 rad of the model's turning) was the gyro's
    assert pred.poses[-1, 2] == pytest.approx(model_turn, abs=0.3 * (1 + abs(factor)) + 1e-6)
    said = [(message, error) for cause, message, error in warnings if cause == 'imu_contradicts']
    assert len(said) == 1 and said[0][1] is True
    assert hint in said[0][0] and 'is not used' in said[0][0]
    assert odometer.counters['imu_interval_contradicts'] > 350
    state = odometer.gyro.state()
    assert state['contradicts_wheels'] == 1.0 and state['gain'] == 1.0


@pytest.mark.parametrize('factor', [0.0, 0.3, 0.6, 1.0, 1.4])
def test_a_gyro_that_turns_less_than_the_model_is_a_skid_and_is_used(factor):
    # ice (the robot does not turn), a skid, a calibrated model: all plausible
    warnings = []
    odometer = _odometer('fuse', warnings)
    wheels = _drive()
    pred = odometer.predict(wheels, imu=_gyro(wheels, factor * MODEL_RATE))
    assert pred.poses[-1, 2] == pytest.approx(factor * MODEL_RATE * 19.95, abs=1e-6)
    assert not any(cause == 'imu_contradicts' for cause, _, _ in warnings)


def test_a_gyro_that_agrees_again_is_taken_back():
    warnings = []
    odometer = _odometer('fuse', warnings)
    wheels = _drive()
    imu = _gyro(wheels, -0.6 * MODEL_RATE)
    rate = np.where(imu.t_ns > 10 * NS, 0.6 * MODEL_RATE, imu.yaw_rate)  # fixed at 10 s
    odometer.predict(wheels, imu=ImuSamples(imu.t_ns, rate))
    said = [m for cause, m, _ in warnings if cause == 'imu_contradicts']
    assert len(said) == 2 and 'agrees with the wheels again' in said[1]
    assert odometer.gyro.last.yaw_from_gyro


def test_diagnostics_warn_while_the_gyro_contradicts_the_wheels():
    from diagnostic_msgs.msg import DiagnosticStatus
    from skidkin_ros.node.diagnostics import StatusReport
    odometer = _odometer('fuse')
    wheels = _drive(seconds=5.0)
    odometer.predict(wheels, imu=_gyro(wheels, -MODEL_RATE))
    counters = collections.Counter(odometer.counters)
    counters['integrated'] = 1
    status = StatusReport().status('odom', OdometryConfig.from_flat({'imu.mode': 'fuse'}),
                                   counters, False, 0.01, imu=odometer.gyro.state())
    assert status.level == DiagnosticStatus.WARN
    assert 'the gyro contradicts the wheels' in status.message and 'z up' in status.message
    values = {kv.key: kv.value for kv in status.values}
    assert values['imu.contradicts_wheels'] == '1'


def test_a_gyro_clock_far_ahead_of_the_wheels_is_said_not_silently_unused():
    # The wheel driver restarts on a clock an hour behind, the IMU's does not: every gyro
    # sample is later than every wheel interval (counted as no_history, silently).
    warnings = []
    odometer = _odometer('fuse', warnings)
    rate = 0.6 * MODEL_RATE
    ms10, ms50 = 10_000_000, 50_000_000
    _feed(odometer, [HOUR + k * ms50 for k in range(100)],
          [HOUR - NS + k * ms10 for k in range(600)], rate)
    _feed(odometer, [10 * NS + k * ms50 for k in range(100)],
          [HOUR + 5 * NS + k * ms10 for k in range(500)], rate)
    counts = odometer.counters
    assert counts['stamp_reset'] == 1 and counts['imu_interval_clock_ahead'] > 90
    said = [m for cause, m, _ in warnings if cause == 'imu_clock_ahead']
    assert len(said) == 1 and 's ahead of the wheel stamps' in said[0]
    assert not odometer.gyro.last.yaw_from_gyro   # the model carries on
