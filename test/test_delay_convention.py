"""The reference's delay measured exactly, online and offline: a half-period lead explained.

A noise-free reference of the simulator's truth, stamped a known delay late (or early), at 10 and
30 Hz, against wheels at 20 and 50 Hz. The simulator's wheel speeds are sampled at the stamp, so
``interval: midpoint`` (the trapezoid) integrates the true motion: the online check
(core/online/delay.py) and the offline rule (``skidkin diagnose``'s lag scan) both measure the
delay to within one lag step (10 ms). Under ``interval: ending`` each speed is taken as the mean
over the period it ends, so the wheels' integrated motion leads the truth by half a wheel period,
and both read the reference that much later: the shared rule measures the delay against the
motion the file's convention integrates (fault matrix C291, N195).
"""

from dataclasses import replace

import numpy as np
import pytest
from skidkin_ros.core.calibration.diagnosis.options import DiagnosisOptions
from skidkin_ros.core.calibration.diagnosis.residuals import pose_samples
from skidkin_ros.core.calibration.diagnosis.state import ModelState
from skidkin_ros.core.calibration.diagnosis.tracing import lag_scan
from skidkin_ros.core.calibration.lag import LAG_STEP_S
from skidkin_ros.core.drive import Drive, PoseTrack
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.online import online_odometer
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate

MODEL = 'edd_asymmetric'
FILE = {'model': MODEL, 'robot': 'sim_husky',
        **{f'models.{MODEL}.{k}': v for k, v in DEFAULT_TRUE_PARAMS.items()},
        f'models.{MODEL}.noise.calibrated': True, 'online.enabled': True,
        'online.delay_learn': 0.0, 'online.delay_tolerance': 0.06}
WHEEL_HZ = (20.0, 50.0)
REFERENCE_HZ = (10.0, 30.0)
DELAYS_S = (0.1, -0.2)


@pytest.fixture(scope='module', params=WHEEL_HZ)
def sim(request):
    return simulate(SimConfig(duration_s=40.0, seed=9, wheel_rate_hz=request.param))


def _reference(sim, rate_hz, delay_s):
    t = np.arange(sim.start_ns + 1_000_000_000, sim.end_ns - 1_000_000_000,
                  int(round(1e9 / rate_hz)))
    truth = sim.truth_at(t)
    return PoseTrack(t + int(round(delay_s * 1e9)), truth.x, truth.y, truth.yaw)


def _online(sim, reference, interval, offset_s):
    config = OdometryConfig.from_flat({**FILE, 'interval': interval,
                                       'online.time_offset': offset_s})
    odometer = online_odometer(config)
    odometer.predict(sim.wheels, reference=reference)
    return odometer.learner.summary()['measured_delay']


def _offline(sim, reference, interval):
    options = replace(DiagnosisOptions(), interval=interval)
    drive = Drive('late', sim.wheels, reference, None, {})
    state = ModelState((), dict(DEFAULT_TRUE_PARAMS), {})
    samples = pose_samples([drive], state.bind(MODEL, sim.config.geometry), options)
    lag, _ = lag_scan([drive], samples, state, MODEL, sim.config.geometry, options)
    return lag


def _lead(sim, interval):
    """Half a wheel period under ending (the wheels' motion leads), none under midpoint."""
    return 0.5 / sim.config.wheel_rate_hz if interval == 'ending' else 0.0


@pytest.mark.parametrize('interval', ['midpoint', 'ending'])
def test_online_check_measures_the_delay_against_the_integrated_motion(sim, interval):
    errors = []
    for rate in REFERENCE_HZ:
        for delay in DELAYS_S:
            # the right offset in force: what is measured is the delay itself (no correction)
            measured = _online(sim, _reference(sim, rate, delay), interval, delay)
            errors.append(measured - delay)
    # a wrong offset (0 for a reference 0.1 s late): the same delay, measured from elsewhere
    errors.append(_online(sim, _reference(sim, 10.0, 0.1), interval, 0.0) - 0.1)
    lead = _lead(sim, interval)
    assert np.all(np.abs(np.array(errors) - lead) <= LAG_STEP_S + 1e-9), (errors, lead)


@pytest.mark.parametrize('interval', ['midpoint', 'ending'])
def test_offline_lag_rule_shares_it(sim, interval):
    errors = [_offline(sim, _reference(sim, rate, delay), interval) - delay
              for rate in REFERENCE_HZ for delay in DELAYS_S]
    lead = _lead(sim, interval)
    assert np.all(np.abs(np.array(errors) - lead) <= LAG_STEP_S + 1e-9), (errors, lead)
