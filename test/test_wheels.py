"""The wheel rules the node and the bag reader share (core.odometry.wheels), without ROS."""

import math

import numpy as np
import pytest
from skidkin_ros.adapters.bag_reader import open_recording
from skidkin_ros.adapters.bag_writer import BagWriter
from skidkin_ros.core.odometry.wheels import (check_velocity_count, DuplicateJointError,
                                              joint_indices, MalformedMessageError,
                                              MissingJointError, pair_wheel_streams, Pairing,
                                              repeated_names, side_speed, speeds_at,
                                              WheelPairer)

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
