"""The wheel rules the node and the bag reader share (core.odometry.wheels), without ROS."""

import math

import numpy as np
import pytest
from skidkin_ros.adapters.bag_reader import open_recording
from skidkin_ros.adapters.bag_writer import BagWriter
from skidkin_ros.core.odometry.wheels import (check_position_count, check_velocity_count,
                                              DuplicateJointError, joint_indices,
                                              MalformedMessageError, MissingJointError,
                                              pair_wheel_streams, Pairing, repeated_names,
                                              side_speed, speeds_at, WheelPairer, WheelSignal)

T0_NS = 1_700_000_000_000_000_000
MS = 1_000_000


def test_joint_indices_find_the_wheels_and_name_what_is_missing():
    names = ['lidar_tilt', 'rear_left', 'front_right', 'front_left', 'rear_right']
    assert joint_indices(names, ['front_left', 'rear_left'], ['front_right', 'rear_right']) == (
        (3, 1), (2, 4))
    with pytest.raises(MissingJointError, match=r"\['mid_left'\].*left_wheel_joints"):
        joint_indices(names, ['mid_left'], ['front_right'])
    check_velocity_count(3, 3)
    check_velocity_count(3, 4)
    with pytest.raises(MalformedMessageError, match='3 names but only 2 velocities'):
        check_velocity_count(3, 2)


def test_a_missing_joint_message_shows_a_bounded_list_of_names():
    names = [f'joint_{i}' for i in range(100_000)]  # a hostile driver's list
    with pytest.raises(MissingJointError) as err:
        joint_indices(names, ['left'], ['right'])
    assert "it has 100000: ['joint_0', 'joint_1'," in str(err.value)
    assert len(str(err.value)) < 1000


def test_a_wheel_joint_listed_twice_is_refused_naming_it_and_where():
    names = ['front_left', 'rear_left', 'front_right', 'rear_right', 'front_left']
    with pytest.raises(DuplicateJointError, match=r"'front_left' at \[0, 4\]"):
        joint_indices(names, ['front_left', 'rear_left'], ['front_right', 'rear_right'])
    # Another joint listed twice does not touch the wheels: the indices are found, and named.
    names = ['caster', 'front_left', 'caster', 'front_right', 'arm', 'arm', 'caster']
    assert joint_indices(names, ['front_left'], ['front_right']) == ((1,), (3,))
    assert repeated_names(names) == ['caster', 'arm']
    assert repeated_names(['a', 'b']) == []


def test_bag_reader_drops_messages_with_a_wheel_joint_listed_twice(tmp_path):
    """The node's rule offline: a repeated wheel joint is refused, a repeated other joint not."""
    good = ['l1', 'r1', 'arm', 'arm']
    with BagWriter(tmp_path / 'bag') as bag:
        bag.write_joint_state('/joint_states', T0_NS, good, [1.0, 2.0, 0.0, 0.0])
        bag.write_joint_state('/joint_states', T0_NS + 10 * MS, ['l1', 'r1', 'l1'],
                              [1.0, 2.0, 9.0])
        bag.write_joint_state('/joint_states', T0_NS + 20 * MS, good, [1.0, 2.0, 0.0, 0.0])
    with open_recording(tmp_path / 'bag') as bag:
        wheels = bag.read_wheels(left_joints=['l1'], right_joints=['r1'])
        assert any('1 with a wheel joint listed twice' in note for note in bag.notes)
    np.testing.assert_array_equal((wheels.t_ns - T0_NS) // MS, [0, 20])


def test_side_speed_is_the_correctly_rounded_mean_and_keeps_identical_values():
    values = [0.1, 0.2, 0.3]
    assert side_speed(values) == math.fsum(values) / 3
    assert side_speed(values) != float(np.mean(values))  # the rule numpy's sum would break
    assert side_speed([0.1, 0.1, 0.1]) == 0.1             # (0.1 + 0.1 + 0.1) / 3 is not 0.1
    assert speeds_at([9.0, 0.1, 0.2, 0.3, 2.0], (1, 2, 3), (4,)) == (side_speed(values), 2.0)


def test_pairer_pairs_within_tolerance_stamped_with_the_later_time():
    pairer = WheelPairer(tolerance_ns=50 * MS)
    assert pairer.offer('left', 0, 1.0) == (Pairing.WAITING, None)
    assert pairer.offer('right', 30 * MS, 2.0) == (Pairing.PAIRED, (30 * MS, 1.0, 2.0))
    # The right side goes silent: the waiting left value is replaced, and that is reported.
    assert pairer.offer('left', 100 * MS, 3.0) == (Pairing.WAITING, None)
    assert pairer.offer('left', 110 * MS, 4.0) == (Pairing.UNPAIRED, None)
    # A right value too late for the waiting left one drops it and waits itself.
    assert pairer.offer('right', 200 * MS, 5.0) == (Pairing.UNPAIRED, None)
    assert pairer.offer('left', 210 * MS, 6.0) == (Pairing.PAIRED, (210 * MS, 6.0, 5.0))
    pairer.offer('left', 300 * MS, 7.0)
    pairer.clear()
    assert pairer.offer('right', 301 * MS, 8.0) == (Pairing.WAITING, None)
    assert pairer.last_seen_ns == {'left': 300 * MS, 'right': 301 * MS}


def test_pair_wheel_streams_feeds_the_pairer_in_order():
    events = [('left', 0, 0.0), ('right', 5, 10.0), ('left', 10, 1.0), ('right', 15, 11.0),
              ('left', 20, 2.0), ('left', 30, 3.0), ('right', 30, 12.0)]
    samples, unpaired = pair_wheel_streams(events, tolerance_ns=50)
    assert samples == [(5, 0.0, 10.0), (15, 1.0, 11.0), (30, 3.0, 12.0)]
    assert unpaired == 1


def test_bag_reader_pairs_float64_topics_by_the_node_rule(tmp_path):
    """Two Float64 topics are paired on receive time within pair_tolerance, as odom_node does.

    (Before, the reader merged them as a zero-order-hold union: samples at 5, 10, 15, 20 and
    30 ms, where the node integrates three pairs.)
    """
    with BagWriter(tmp_path / 'bag') as bag:
        for k, t_ms in enumerate([0, 10, 20, 30]):
            bag.write_float64('/left_wheel/speed', T0_NS + t_ms * MS, float(k))
        for k, t_ms in enumerate([5, 15, 31]):
            bag.write_float64('/right_wheel/speed', T0_NS + t_ms * MS, 10.0 + k)
    with open_recording(tmp_path / 'bag') as bag:
        wheels = bag.read_wheels()  # no JointState: the left/right Float64 pair is detected
        assert any('no JointState topic' in n for n in bag.notes)
        assert any('paired on bag receive time within pair_tolerance 0.05 s' in n
                   and '1 value(s) without a partner' in n for n in bag.notes)
        assert bag.wheel_input['input'] == 'wheel_topics'
    np.testing.assert_array_equal((wheels.t_ns - T0_NS) // MS, [5, 15, 31])
    np.testing.assert_array_equal(wheels.omega_l, [0, 1, 3])
    np.testing.assert_array_equal(wheels.omega_r, [10, 11, 12])
    with open_recording(tmp_path / 'bag') as bag:  # a tighter tolerance pairs fewer
        tight = bag.read_wheels(pair_tolerance_s=0.004)
    np.testing.assert_array_equal((tight.t_ns - T0_NS) // MS, [31])


def test_bag_reader_takes_a_side_speed_as_the_node_does(tmp_path):
    names = ['l1', 'l2', 'l3', 'r1']
    with BagWriter(tmp_path / 'bag') as bag:
        for i in range(3):
            bag.write_joint_state('/joint_states', T0_NS + i * 10 * MS, names,
                                  [0.1, 0.2, 0.3, 1.0])
    with open_recording(tmp_path / 'bag') as bag:
        wheels = bag.read_wheels(left_joints=['l1', 'l2', 'l3'], right_joints=['r1'])
    assert wheels.omega_l.tolist() == [side_speed([0.1, 0.2, 0.3])] * 3


# ------------------------------------------------------------------ wheel_signal
def _take(signal, t_s, left, right, velocity=(9.0, 9.0)):
    positions = None if left is None else (left, right)
    return signal.take(int(round(t_s * 1e9)), *velocity, positions)


def test_position_signal_integrates_the_travel_between_positions():
    signal = WheelSignal('position', 50.0)
    first = _take(signal, 0.0, (1.0, 1.2), (2.0, 2.0))
    assert first.speeds == (9.0, 9.0) and signal.in_use == 'position'  # nothing to difference
    # left joints travel 0.1 and 0.3 rad in 0.1 s: mean 2 rad/s; right -0.05 rad: -0.5 rad/s
    taken = _take(signal, 0.1, (1.1, 1.5), (1.95, 1.95))
    assert taken.speeds == pytest.approx((2.0, -0.5)) and not taken.switched
    assert signal.in_use == 'position'


@pytest.mark.parametrize('before, after, travel', [
    (3.0, -3.0, 2 * math.pi - 6.0),          # [-pi, pi) driver, forward through +pi
    (-3.0, 3.0, 6.0 - 2 * math.pi),          # backward through -pi
    (6.2, 0.1, 0.1 + 2 * math.pi - 6.2),     # [0, 2 pi) driver
    (100.0, 100.5, 0.5),                     # an unwrapped angle far from zero
])
def test_a_wrapped_continuous_joint_is_taken_the_short_way_round(before, after, travel):
    signal = WheelSignal('position', 50.0)
    _take(signal, 0.0, (before,), (before,))
    taken = _take(signal, 0.05, (after,), (after,))
    assert taken.speeds == pytest.approx((travel / 0.05, travel / 0.05))


def test_hostile_positions_are_rejected_and_counted_like_bad_speeds():
    signal = WheelSignal('position', 20.0)
    _take(signal, 0.0, (10.0,), (10.0,))
    for bad in (math.nan, math.inf, -math.inf):
        taken = _take(signal, 0.05, (bad,), (10.0,))
        assert taken.speeds is None and taken.cause == 'non_finite'
    # the last finite positions are kept: the next travel is measured from them
    assert _take(signal, 0.1, (10.2,), (10.2,)).speeds == pytest.approx((2.0, 2.0))
    # a counter reset (a huge step backwards) exceeds max_wheel_speed * dt: rejected ...
    reset = _take(signal, 0.15, (0.0,), (10.3,))
    assert reset.speeds is None and reset.cause == 'implausible'
    assert 'left wheel position jumped' in reset.detail and 'max_wheel_speed 20' in reset.detail
    # ... and the positions are differenced from the new ones on, not refused forever
    assert _take(signal, 0.2, (0.1,), (10.4,)).speeds == pytest.approx((2.0, 2.0))
    # a message without positions is refused when positions are required
    missing = _take(signal, 0.25, None, None)
    assert missing.speeds is None and missing.cause == 'no_position'


def test_auto_uses_positions_that_change_and_velocities_otherwise():
    signal = WheelSignal('auto', 50.0)
    assert signal.in_use == 'velocity'
    # a driver whose positions never change: the velocities are integrated
    for i in range(3):
        taken = _take(signal, 0.1 * i, (0.0,), (0.0,), velocity=(1.0, 2.0))
        assert taken.speeds == (1.0, 2.0) and not taken.switched
    # positions that change: they take over, said once; the interval of the first change is
    # still the velocities' (the count it holds was partly integrated by them already)
    taken = _take(signal, 0.3, (0.5,), (0.2,), velocity=(1.0, 2.0))
    assert taken.speeds == (1.0, 2.0) and taken.switched == 'position'
    taken = _take(signal, 0.4, (1.0,), (0.4,))
    assert taken.speeds == pytest.approx((5.0, 2.0)) and not taken.switched
    # a repeated position is no travel (a quantised encoder between counts), not a switch
    taken = _take(signal, 0.45, (1.0,), (0.4,))
    assert taken.speeds == (0.0, 0.0) and not taken.switched
    # mixed: a message without positions (or with non-finite ones) uses its velocities, and
    # the next positions are differenced from a new reference, never across that interval
    taken = _take(signal, 0.5, None, None, velocity=(3.0, 3.0))
    assert taken.speeds == (3.0, 3.0) and taken.switched == 'velocity'
    assert _take(signal, 0.6, (math.nan,), (0.6,), velocity=(4.0, 4.0)).speeds == (4.0, 4.0)
    assert _take(signal, 0.7, (2.0,), (0.7,), velocity=(4.0, 4.0)).speeds == (4.0, 4.0)
    taken = _take(signal, 0.8, (2.3,), (0.8,))
    assert taken.speeds == pytest.approx((3.0, 1.0)) and taken.switched == 'position'


def test_velocity_signal_ignores_positions_and_counts_are_checked():
    signal = WheelSignal('velocity', 50.0)
    assert _take(signal, 0.0, (1.0,), (1.0,)).speeds == (9.0, 9.0)
    assert _take(signal, 0.1, (99.0,), (math.nan,)).speeds == (9.0, 9.0)
    assert check_position_count(4, 0) is False and check_position_count(4, 4) is True
    with pytest.raises(MalformedMessageError, match='4 names but 3 positions'):
        check_position_count(4, 3)
    with pytest.raises(ValueError, match='velocity, position, auto'):
        WheelSignal('encoder')
