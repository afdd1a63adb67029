"""The one integrator: exact SE(2) steps, batch == streaming, and the sample checks."""

import math

import numpy as np
import pytest
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.integrator import (body_increment, IntegratorLimits, rollout,
                                                  rollout_segments, SampleStatus, SMALL_ANGLE_RAD,
                                                  stream_twists, StreamingIntegrator)
from skidkin_ros.errors import ParameterError

GEOM = Geometry(0.3, 1.2)


def test_constant_arc_is_exact_even_with_one_big_step():
    v, w, t = 1.0, 0.5, 3.0
    radius = v / w
    expected = [radius * math.sin(w * t), radius * (1 - math.cos(w * t)), w * t]
    one_step = rollout(np.array([[v, 0.0, w]]), np.array([t]))[-1]
    many = rollout(np.tile([v, 0.0, w], (300, 1)), np.full(300, t / 300))[-1]
    np.testing.assert_allclose(one_step, expected, atol=1e-12)
    np.testing.assert_allclose(many, expected, atol=1e-9)


def test_lateral_velocity_is_rotated_with_the_body():
    # v_y only, quarter turn: the robot moves on a circle, ending at (-R, R)
    v_y, w, t = 1.0, math.pi / 2, 1.0
    r = v_y / w
    end = rollout(np.array([[0.0, v_y, w]]), np.array([t]))[-1]
    np.testing.assert_allclose(end, [-r, r, math.pi / 2], atol=1e-12)


@pytest.mark.parametrize('omega', [0.0, 1e-12, SMALL_ANGLE_RAD * 0.999, SMALL_ANGLE_RAD,
                                   SMALL_ANGLE_RAD * 1.001])
def test_small_rotation_branch_is_continuous(omega):
    dx, dy, dth = body_increment(2.0, 0.5, omega, 1.0)
    # closed form evaluated in extended precision as reference
    w = np.longdouble(omega)
    if w == 0:
        ref = (2.0, 0.5)
    else:
        s = np.sin(w) / w
        c = (1 - np.cos(w)) / w
        ref = (float(2 * s - 0.5 * c), float(2 * c + 0.5 * s))
    assert abs(dx - ref[0]) < 1e-12 and abs(dy - ref[1]) < 1e-12
    assert dth == omega


@pytest.mark.parametrize('interval, pick', [
    ('starting', lambda w: w[:-1]),
    ('ending', lambda w: w[1:]),
    ('midpoint', lambda w: (w[:-1] + w[1:]) * 0.5)])
def test_batch_and_streaming_agree_bit_for_bit(interval, pick):
    rng = np.random.default_rng(1)
    n = 400
    t_ns = np.cumsum(rng.integers(20_000_000, 80_000_000, n)).astype(np.int64)
    wl, wr = rng.uniform(-5, 5, (2, n))
    bound = get_model('edd_asymmetric').bind(
        {'alpha_l': 0.9, 'alpha_r': 0.8, 'x_v': -0.2, 'y_l': 0.8, 'y_r': -0.7}, GEOM)
    stream = StreamingIntegrator(bound, IntegratorLimits(max_dt_s=1.0), interval)
    streamed = np.array([stream.step(int(t), a, b).pose for t, a, b in zip(t_ns, wl, wr)])
    # Each convention integrates its own speeds over [t_k-1, t_k] (written out here, not taken
    # from the interval module), and the batch rollout of held_speeds is the same.
    twist = bound.twist(pick(wl), pick(wr))
    batch = rollout(twist, np.diff(t_ns) * 1e-9, (0.0, 0.0, 0.0))
    assert np.array_equal(streamed, batch)
    held = stream_twists(bound, t_ns, wl, wr, interval=interval)[1][0]
    assert np.array_equal(rollout(held[:-1], np.diff(t_ns) * 1e-9), batch)
    # The published twist is always the newest sample's.
    assert stream.held_twist.tolist() == list(bound.twist(wl[-1], wr[-1]))


def test_the_default_interval_is_ending_and_a_bad_one_is_refused():
    bound = get_model('ideal_dd').bind({}, GEOM)
    stream = StreamingIntegrator(bound)
    stream.step(0, 0.0, 0.0)
    # ending: the new sample's speeds drive the robot up to its stamp (starting would not move)
    assert stream.step(100_000_000, 2.0, 2.0).pose[0] == pytest.approx(2.0 * 0.3 * 0.1)
    with pytest.raises(ParameterError, match='ending, starting, midpoint'):
        StreamingIntegrator(bound, interval='end')


def test_rollout_segments_padding_with_zero_dt_keeps_the_end_pose():
    twist = np.array([[[1.0, 0.0, 0.2]] * 3, [[1.0, 0.0, 0.2]] * 3])
    dt = np.array([[0.1, 0.1, 0.1], [0.1, 0.2, 0.0]])
    out = rollout_segments(twist, dt, np.zeros((2, 3)))
    np.testing.assert_allclose(out[0, -1], out[1, -1], atol=1e-12)


def _stream(limits=IntegratorLimits(max_dt_s=0.5, max_wheel_speed_rad_s=50.0)):
    return StreamingIntegrator(get_model('ideal_dd').bind({}, GEOM), limits)


@pytest.mark.parametrize('interval, metres', [('starting', 0.03), ('ending', 0.15),
                                              ('midpoint', 0.09)])
def test_each_interval_integrates_its_speeds(interval, metres):
    s = StreamingIntegrator(get_model('ideal_dd').bind({}, Geometry(0.3, 0.5)),
                            IntegratorLimits(max_dt_s=0.5, max_wheel_speed_rad_s=50.0), interval)
    s.step(0, 1.0, 1.0)
    # 0.1 s at 1 rad/s (starting), 5 rad/s (ending) or 3 rad/s (midpoint), r = 0.3 m
    s.step(100_000_000, 5.0, 5.0)
    np.testing.assert_allclose(s.pose, [metres, 0.0, 0.0])


@pytest.mark.parametrize('bad,status', [
    (float('nan'), SampleStatus.NON_FINITE_SPEED), (float('inf'), SampleStatus.NON_FINITE_SPEED),
    (-float('inf'), SampleStatus.NON_FINITE_SPEED), (51.0, SampleStatus.IMPLAUSIBLE_SPEED)])
def test_bad_speeds_are_rejected_and_state_kept(bad, status):
    s = _stream()
    s.step(0, 1.0, 1.0)
    result = s.step(50_000_000, bad, 1.0)
    assert result.status is status and not result.status.accepted
    assert 'left' in result.detail
    s.step(100_000_000, 1.0, 1.0)
    np.testing.assert_allclose(s.pose, [0.03, 0.0, 0.0])  # held speed of the first sample


def test_duplicate_older_and_gap_stamps():
    s = _stream()
    s.step(1_000_000_000, 1.0, 1.0)
    dup = s.step(1_000_000_000, 2.0, 2.0)
    assert dup.status is SampleStatus.DUPLICATE_STAMP and s.held_speeds == (2.0, 2.0)
    old = s.step(900_000_000, 3.0, 3.0)
    assert old.status is SampleStatus.OLDER_STAMP and 'older than previous' in old.detail
    gap = s.step(2_000_000_000, 1.0, 1.0)
    assert gap.status is SampleStatus.GAP
    np.testing.assert_allclose(s.pose, [0.0, 0.0, 0.0])  # nothing integrated across the gap
    s.step(2_100_000_000, 1.0, 1.0)
    np.testing.assert_allclose(s.pose, [0.03, 0.0, 0.0])  # resumed from the sample after it


def test_non_finite_state_is_never_kept():
    class Exploding:

        def twist(self, wl, wr):
            return np.array([np.inf, 0.0, 0.0]) if wl > 0 else np.zeros(3)

    s = StreamingIntegrator(Exploding())
    s.step(0, 1.0, 1.0)
    result = s.step(400_000_000, 1.0, 1.0)
    assert result.status is SampleStatus.NON_FINITE_STATE
    assert np.all(np.isfinite(s.pose)) and np.all(s.pose == 0.0)
