"""Fault rows N23-N28 of docs/fault-matrix.md: hostile or odd JointStates against the real node.

The node subscribes to serialized JointStates and reads them with node.wire; these tests publish
bytes (``Publisher.publish(bytes)``), as a hostile or careless driver on the graph could.
"""

import struct

from node_harness import NS_PER_S, wall_ns
import pytest
from rclpy.serialization import serialize_message

pytestmark = pytest.mark.ros

DT = 20_000_000


def start_ns():
    return wall_ns() - 5 * NS_PER_S


def serialized(rig, t_ns, omega_l, omega_r, extra=(), effort=None, position=True):
    """Return a serialized JointState of the rig's wheels (plus ``extra`` joints at 0 rad/s)."""
    msg = rig.joint_state(t_ns, omega_l, omega_r)
    msg.name = list(msg.name) + list(extra)
    msg.velocity = list(msg.velocity) + [0.0] * len(extra)
    n = len(msg.name)
    if position:
        msg.position = [0.5 * i for i in range(n)]
    msg.effort = list(effort) if effort is not None else [3.0] * n
    return serialize_message(msg)


def uint32_at(data, offset, value):
    out = bytearray(data)
    struct.pack_into('<I', out, offset, value)
    return bytes(out)


def position_count_at(data):
    """Return the byte offset of the position count (after the last wheel joint's name)."""
    last = b'rear_right_wheel_joint\x00'
    end = data.index(last) + len(last)
    return (end + 3) & ~3


def expected_yaw_rate(rig, omega_l, omega_r):
    geometry = rig.node.config.geometry
    return geometry.wheel_radius * (omega_r - omega_l) / geometry.track_width


def test_n23_wrong_position_count_is_refused_not_read_as_velocity(make_rig):
    """Red-team case: position count 4 -> 9 made the reader return the efforts as wheel speeds."""
    rig = make_rig({'model': 'ideal_dd'})
    t0 = start_ns()
    rig.send(serialized(rig, t0, 1.0, 2.0))
    forged = serialized(rig, t0 + DT, 1.0, 2.0, effort=[-8.0, -8.0, 8.0, 8.0])
    # 9 positions span the 4 positions and the velocity sequence: what follows is the effort
    # sequence, which the old reader then returned as the velocities.
    forged = uint32_at(forged, position_count_at(forged), 9)
    rig.send(forged)
    rig.send(serialized(rig, t0 + 2 * DT, 1.0, 2.0))
    rig.drain()
    assert [msg.twist.twist.angular.z for msg in rig.odom] == pytest.approx(
        [expected_yaw_rate(rig, 1.0, 2.0)] * 2)
    assert rig.node.counters['malformed_message'] == 1
    assert 'does not deserialize' in rig.node.last_warnings['malformed_message']


def test_n24_message_cut_inside_the_effort_array_is_refused(make_rig):
    rig = make_rig({'model': 'ideal_dd'})
    t0 = start_ns()
    rig.send(serialized(rig, t0, 1.0, 2.0))
    rig.send(serialized(rig, t0 + DT, 1.0, 2.0)[:-12])  # the last effort value cut
    rig.drain()
    assert len(rig.odom) == 1 and rig.node.counters['integrated'] == 0
    assert rig.node.counters['malformed_message'] == 1


def test_n25_names_the_fast_reader_leaves_are_read_by_rclpy(make_rig):
    """Red-team case: an unrelated joint's non-UTF-8 name (rclpy takes it) dropped all messages."""
    rig = make_rig({'model': 'ideal_dd'})
    t0 = start_ns()
    for i in range(3):
        data = serialized(rig, t0 + i * DT, 1.0, 2.0, extra=['caster_XX'])
        rig.send(data.replace(b'caster_XX', b'caster_\xff\xfe'))
    rig.drain()
    assert [msg.twist.twist.angular.z for msg in rig.odom] == pytest.approx(
        [expected_yaw_rate(rig, 1.0, 2.0)] * 3)
    assert rig.node.counters['read_by_rclpy'] == 3 and rig.node.counters['callback_error'] == 0


def test_n26_forged_name_count_is_refused_and_the_next_sample_integrated(make_rig):
    """Red-team case: n_names = 2**32 - 1 and 1 MB of zeros stalled the node 0.25 s per MB."""
    rig = make_rig({'model': 'ideal_dd'})
    t0 = start_ns()
    rig.send(serialized(rig, t0, 1.0, 2.0))
    valid = serialized(rig, t0 + DT, 1.0, 2.0)
    names_at = valid.index(b'front_left_wheel_joint\x00') - 8  # the name count
    rig.send(uint32_at(valid[:names_at + 4], names_at, 2**32 - 1) + bytes(1_000_000))
    rig.send(serialized(rig, t0 + 2 * DT, 1.0, 2.0))
    rig.drain()
    assert rig.node.counters['malformed_message'] == 1
    assert 'claims 4294967295 joint names' in rig.node.last_warnings['malformed_message']
    assert len(rig.odom) == 2 and rig.node.counters['integrated'] == 1


def test_n27_wheel_joint_listed_twice_is_refused_naming_it(make_rig):
    rig = make_rig({'model': 'ideal_dd'})
    t0 = start_ns()
    rig.send(serialized(rig, t0, 1.0, 2.0, extra=['front_left_wheel_joint']))
    rig.drain()
    assert not rig.odom and rig.node.counters['duplicate_joint'] == 1
    assert "'front_left_wheel_joint' at [0, 4]" in rig.node.last_warnings['duplicate_joint']
    rig.send(serialized(rig, t0 + DT, 1.0, 2.0))  # the same joints once each: integrated
    rig.drain()
    assert len(rig.odom) == 1


def test_n28_other_joint_listed_twice_is_integrated_with_one_warning(make_rig):
    rig = make_rig({'model': 'ideal_dd'})
    warned = []
    warn = rig.node._warn

    def counting_warn(cause, message, error=False):
        warned.append(cause)
        warn(cause, message, error)

    rig.node._warn = counting_warn
    t0 = start_ns()
    for i in range(3):
        rig.send(serialized(rig, t0 + i * DT, 1.0, 2.0, extra=['caster', 'arm', 'caster']))
    rig.drain()
    assert len(rig.odom) == 3 and rig.node.counters['duplicate_joint'] == 0
    assert warned == ['repeated_joint']  # once for the name list, not once per message
    assert "['caster']" in rig.node.last_warnings['repeated_joint']
