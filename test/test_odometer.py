"""The odometer: the node's per-sample rules in plain numbers, without ROS."""

import collections

import numpy as np
import pytest
from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.integrator import IntegratorLimits
from skidkin_ros.core.odometry.odometer import Odometer, predict_wheels, SampleRules

NS = 1_000_000_000
DT = 20_000_000
NOW = 1_000 * NS
CALIBRATED = {'model': 'edd_symmetric', 'models.edd_symmetric.noise.calibrated': True,
              'models.edd_symmetric.alpha': 0.9, 'models.edd_symmetric.b_hat': 0.7}


def odometer(flat=None, **listeners):
    return Odometer.from_config(OdometryConfig.from_flat(flat or {}), **listeners)


def test_zero_and_future_stamps_follow_the_rules():
    warnings = []
    odo = odometer(warn=lambda cause, message, error=False: warnings.append(cause))
    assert odo.joint_sample(0, 1.0, 1.0, NOW) is None
    assert odo.joint_sample(NOW + NS, 1.0, 1.0, NOW) is None  # 1 s ahead > 0.5 s
    assert odo.counters['zero_stamp'] == 1 and odo.counters['future_stamp'] == 1
    assert warnings == ['zero_stamp', 'future_stamp']
    assert odo.joint_sample(NOW + NS // 4, 1.0, 1.0, NOW).t_ns == NOW + NS // 4  # within 0.5 s
    lenient = odometer({'zero_stamp_uses_receive_time': True, 'future_tolerance': 2.0})
    assert lenient.joint_sample(0, 1.0, 1.0, NOW).t_ns == NOW
    assert lenient.joint_sample(NOW + NS, 1.0, 1.0, NOW) is not None


def test_duplicate_stamp_updates_the_speeds_without_an_output():
    fresh = []
    odo = odometer(fresh=lambda: fresh.append(1))
    odo.joint_sample(NOW, 1.0, 1.0, NOW)
    assert odo.joint_sample(NOW, 3.0, 3.0, NOW) is None
    estimate = odo.joint_sample(NOW + DT, 3.0, 3.0, NOW + DT)
    assert estimate.pose[0] == pytest.approx(0.1651 * 3.0 * 0.02, abs=1e-15)
    assert odo.counters['duplicate'] == 1 and odo.counters['published'] == 2
    assert len(fresh) == 3  # every accepted sample, published or not


def test_max_rate_caps_the_output_not_the_integration():
    odo = odometer({'max_rate': 10.0})
    out = [odo.joint_sample(NOW + i * DT, 2.0, 2.0, NOW + i * DT) for i in range(11)]
    assert [i for i, e in enumerate(out) if e is not None] == [0, 5, 10]
    assert odo.counters['rate_limited'] == 8 and odo.counters['integrated'] == 10
    assert out[10].pose[0] == pytest.approx(0.1651 * 2.0 * 0.2, abs=1e-15)


def test_published_stamp_carries_the_model_time_offset():
    flat = {'model': 'augmented', 'augmented.base': 'ideal_dd',
            'augmented.extensions': 'time_offset', 'augmented.time_offset.offset_s': 0.08}
    odo = odometer(flat)
    assert odo.joint_sample(NOW, 1.0, 1.0, NOW).t_ns == NOW + 80_000_000
    wheels = WheelSamples([NOW, NOW + DT], [1.0, 1.0], [1.0, 1.0])
    assert odo.predict(wheels).t_ns.tolist() == [NOW + 80_000_000, NOW + DT + 80_000_000]


def test_wheel_topics_are_paired_before_integration():
    warnings = {}
    odo = odometer(warn=lambda cause, message, error=False: warnings.update({cause: message}))
    assert odo.wheel_sample('left', 2.0, NOW) is None
    first = odo.wheel_sample('right', 4.0, NOW + 10_000_000)
    assert first.t_ns == NOW + 10_000_000 and first.twist[2] > 0.0
    assert odo.wheel_sample('left', 2.0, NOW + 30_000_000) is None
    assert odo.wheel_sample('left', 2.0, NOW + 50_000_000) is None  # the right side is silent
    assert odo.counters['unpaired'] == 1
    assert warnings['unpaired'].startswith('right wheel speed is stale (last sample 0.040 s ago)')
    odo.reset()
    # A reset changes the pose only: the left value waiting for its partner pairs as before.
    assert odo.wheel_sample('right', 4.0, NOW + 60_000_000) is not None


def test_predict_is_the_node_pipeline_sample_for_sample():
    """Every published estimate is the prediction at its stamp: the node's path is predict's."""
    rng = np.random.default_rng(0)
    t_ns = NOW + np.cumsum(rng.integers(5, 30, 200)) * 1_000_000
    t_ns[50] = t_ns[49]            # a duplicate stamp
    t_ns[120:] += NS               # a gap
    wl, wr = rng.uniform(-3, 3, 200), rng.uniform(-3, 3, 200)
    wl[80] = np.nan
    wr[150] = 60.0                 # a spike: a wheel glitch (uniform speeds jump 6 rad/s at most)
    config = OdometryConfig.from_flat({**CALIBRATED, 'max_wheel_acceleration': 1000.0})
    live = Odometer.from_config(config)
    estimates = {}
    for t, left, right in zip(t_ns.tolist(), wl, wr):
        estimate = live.joint_sample(t, left, right, t)
        if estimate is not None:
            estimates[estimate.t_ns] = estimate
    prediction = Odometer.from_config(config).predict(WheelSamples(t_ns, wl, wr))
    rows = {}
    for i, t in enumerate(prediction.t_ns.tolist()):
        if prediction.accepted[i]:
            rows.setdefault(t, i)  # a duplicate stamp publishes its first sample only
    assert len(estimates) == 197  # 200 less the NaN, the spike and the duplicate's second sample
    for t, estimate in estimates.items():
        assert estimate.pose == tuple(prediction.poses[rows[t]])
        assert estimate.twist == tuple(prediction.twists[rows[t]])
    assert live.counters == collections.Counter(
        {'integrated': 195, 'first': 1, 'gap': 1, 'duplicate': 1, 'non_finite': 1,
         'wheel_jump': 1, 'published': 197})
    plain = predict_wheels(WheelSamples(t_ns, wl, wr), config.bound_model(), config.limits)
    assert np.array_equal(plain.poses, prediction.poses)


def test_configure_keeps_pose_and_covariance_and_reset_sets_them():
    odo = odometer(CALIBRATED)
    for i in range(10):
        odo.joint_sample(NOW + i * DT, 2.0, 3.0, NOW + i * DT)
    pose, cov = odo.pose, odo.covariance.cov
    assert cov[0, 0] > 1e-9
    odo.configure(OdometryConfig.from_flat({**CALIBRATED, 'max_rate': 5.0, 'pair_tolerance': 1.0}))
    assert np.array_equal(odo.pose, pose) and np.array_equal(odo.covariance.cov, cov)
    assert odo.rules == SampleRules(False, 0.5, 1.0, 5.0)
    block = np.diag([1.0, 2.0, 3.0])
    odo.reset((1.0, 2.0, 0.5), block)
    assert odo.pose.tolist() == [1.0, 2.0, 0.5]
    np.testing.assert_allclose(odo.covariance.cov, block + 1e-9 * np.eye(3), rtol=0, atol=1e-15)
    assert odo.last_published_t_ns is None


def test_limits_come_from_the_configuration():
    config = OdometryConfig.from_flat({'max_dt': 0.25, 'max_wheel_speed': 40.0,
                                       'max_wheel_acceleration': 300.0})
    assert config.limits == IntegratorLimits(max_dt_s=0.25, max_wheel_speed_rad_s=40.0,
                                             max_wheel_acceleration_rad_s2=300.0)
    assert Odometer.from_config(config).integrator.limits == config.limits


def test_a_pose_or_covariance_the_odometry_cannot_hold_is_refused_and_changes_nothing():
    """N30: a pose of 1e308 m was taken, and nothing was published after it."""
    odo = odometer()
    odo.joint_sample(NOW, 1.0, 1.0, NOW)
    odo.joint_sample(NOW + DT, 1.0, 1.0, NOW + DT)
    pose = odo.pose
    refused = [((1e308, 1e308, 0.0), None), ((1.1e9, 0.0, 0.0), None),
               ((0.0, 0.0, float('nan')), None), ((0.0, 0.0, 0.0), np.diag([1e308, 1.0, 1.0])),
               ((0.0, 0.0, 0.0), np.diag([float('inf'), 1.0, 1.0])),
               ((0.0, 0.0, 0.0), np.array([[1.0, 5.0, 0.0], [5.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))]
    for bad_pose, covariance in refused:
        with pytest.raises(ValueError):
            odo.reset(bad_pose, covariance)
        assert np.array_equal(odo.pose, pose)
    odo.reset((1e9, -1e9, 3.0), np.diag([1e12, 1e12, 1e12]))  # the limits themselves are taken
    published = [odo.joint_sample(NOW + k * DT, 1.0, 1.0, NOW + k * DT) for k in range(2, 5)]
    assert published[-1] is not None and np.isfinite(published[-1].pose_covariance).all()


def test_a_stepped_back_input_clock_resets_once_confirmed_and_one_bad_stamp_is_refused():
    """N31: a driver restart locked the node out until its stamps caught up."""
    odo = odometer()
    for k in range(50):
        odo.joint_sample(NOW + k * DT, 1.0, 1.0, NOW + k * DT)
    last = NOW + 49 * DT
    x = odo.pose[0]
    # One corrupt stamp 900 s behind: refused, nothing reset.
    assert odo.joint_sample(NOW - 900 * NS, 1.0, 1.0, last) is None
    assert odo.counters['stamp_step_back'] == 1 and odo.pose[0] == x
    assert odo.joint_sample(last + DT, 1.0, 1.0, last + DT) is not None
    # A driver restart: its clock starts again at 5 s; three samples in a row confirm it.
    restart = 5 * NS
    out = [odo.joint_sample(restart + k * DT, 1.0, 1.0, last + (k + 2) * DT) for k in range(6)]
    assert out[:2] == [None, None] and odo.counters['stamp_reset'] == 1
    assert [e.t_ns for e in out[3:]] == [restart + k * DT for k in range(3, 6)]
    assert odo.pose[0] == pytest.approx(0.1651 * 3 * DT / NS)  # from the origin, new clock
    # A step back shorter than max_stamp_step_back is refused as older, never a reset.
    assert odo.joint_sample(restart + 5 * DT - NS, 1.0, 1.0, last) is None
    assert odo.counters['older'] == 1 and odo.counters['stamp_reset'] == 1


def test_negative_and_stale_stamps_after_a_reset_are_refused():
    """Red-team case: after ~/reset the first stamp was published whatever it was."""
    odo = odometer()
    for k in range(5):
        odo.joint_sample(NOW + k * DT, 1.0, 1.0, NOW + k * DT)
    odo.reset()
    assert odo.joint_sample(-3 * NS, 1.0, 1.0, NOW) is None
    assert odo.counters['negative_stamp'] == 1
    assert odo.joint_sample(1, 1.0, 1.0, NOW) is None  # 1 ns: a stale stamp, not a new clock
    assert odo.counters['stamp_step_back'] == 1
    estimate = odo.joint_sample(NOW + 5 * DT, 1.0, 1.0, NOW + 5 * DT)
    assert estimate is not None and estimate.t_ns == NOW + 5 * DT
    odo.clock_changed()  # a sim-time jump: the old stamps mean nothing, any stamp starts anew
    assert odo.joint_sample(7 * NS, 1.0, 1.0, 7 * NS) is not None


def test_a_wheel_speed_that_jumps_is_rejected_naming_the_side():
    """Red-team case: 90 rad/s spikes under max_wheel_speed were integrated."""
    warnings = []
    odo = odometer(warn=lambda cause, message, error=False: warnings.append((cause, message)))
    speeds = [(2.0, 2.0)] * 5 + [(2.0, 90.0)] + [(2.0, 2.0)] * 5
    for k, (left, right) in enumerate(speeds):
        odo.joint_sample(NOW + 50 * k * 1_000_000, left, right, NOW + 50 * k * 1_000_000)
    assert odo.counters['wheel_jump'] == 1 and odo.counters['integrated'] == 9
    assert odo.pose[0] == pytest.approx(0.1651 * 2.0 * 0.5)  # the spike never moved the robot
    cause, message = warnings[0]
    assert cause == 'wheel_jump' and 'right wheel speed jumped from 2 to 90' in message
    assert 'left' not in message
    # A real step in speed is taken once it is plausible over the time since the last sample.
    odo = odometer({'max_wheel_acceleration': 100.0})
    odo.joint_sample(NOW, 0.0, 0.0, NOW)
    assert odo.joint_sample(NOW + DT, 5.0, 5.0, NOW + DT) is None       # 250 rad/s^2
    assert odo.joint_sample(NOW + 3 * DT, 5.0, 5.0, NOW + 3 * DT) is not None  # 83 rad/s^2


def test_auto_wheel_signal_says_which_signal_it_integrates_and_counts_bad_positions():
    heard, warned = [], []
    config = OdometryConfig.from_flat({'wheel_signal': 'auto', 'max_wheel_speed': 20.0})
    odometer = Odometer.from_config(config, note=heard.append,
                                    warn=lambda cause, message, error=False: warned.append(cause))
    now = 10 ** 12
    for i in range(3):  # positions that never change: the velocities are integrated
        odometer.joint_sample(now + i * 50_000_000, 1.0, 1.0, now + 10 ** 9, ((0.0,), (0.0,)))
    assert heard == [] and odometer.signal.in_use == 'velocity'
    odometer.joint_sample(now + 150_000_000, 1.0, 1.0, now + 10 ** 9, ((0.1,), (0.1,)))
    assert heard == ['wheel signal: integrating the wheel positions (wheel_signal auto)']
    # a counter that steps back 5 rad in 50 ms: rejected and counted like a bad speed
    odometer.joint_sample(now + 200_000_000, 1.0, 1.0, now + 10 ** 9, ((-4.9,), (0.15,)))
    assert odometer.counters['implausible'] == 1 and warned == ['implausible']
    odometer.joint_sample(now + 250_000_000, 1.0, 1.0, now + 10 ** 9, None)
    assert heard[-1] == 'wheel signal: integrating the wheel velocities (wheel_signal auto)'
