"""The node's CDR codecs against two independent serializers: rclpy's and rosbags'."""

from __future__ import annotations

import random

from nav_msgs.msg import Odometry
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import get_typestore, Stores
from sensor_msgs.msg import JointState
from skidkin_ros.node.wire import JointStateReader, OdometryWriter, WireFormatError

NS_PER_S = 1_000_000_000


def _random_joint_state(rng: random.Random) -> JointState:
    msg = JointState()
    msg.header.stamp.sec = rng.randrange(0, 2**31)
    msg.header.stamp.nanosec = rng.randrange(0, NS_PER_S)
    msg.header.frame_id = 'f' * rng.randrange(0, 9)
    n = rng.randrange(0, 6)
    msg.name = [''.join(rng.choice('abcé_') for _ in range(rng.randrange(0, 12)))
                for _ in range(n)]
    msg.position = [rng.uniform(-9, 9) for _ in range(rng.choice((0, n)))]
    msg.velocity = [rng.uniform(-9, 9) for _ in range(rng.choice((0, n, max(n - 1, 0))))]
    msg.effort = [rng.uniform(-9, 9) for _ in range(rng.choice((0, n)))]
    return msg


def test_joint_state_reader_matches_rclpy_on_random_messages() -> None:
    rng = random.Random(7)
    reader = JointStateReader()
    for _ in range(300):
        msg = _random_joint_state(rng)
        t_ns, n_names, key, velocity = reader.read(serialize_message(msg))
        assert t_ns == msg.header.stamp.sec * NS_PER_S + msg.header.stamp.nanosec
        assert n_names == len(msg.name)
        assert reader.names(key) == list(msg.name)
        assert velocity == tuple(msg.velocity)


def test_joint_state_reader_reads_big_endian_cdr_from_rosbags() -> None:
    typestore = get_typestore(Stores.ROS2_JAZZY)
    joint_state = typestore.types['sensor_msgs/msg/JointState']
    header = typestore.types['std_msgs/msg/Header']
    stamp = typestore.types['builtin_interfaces/msg/Time']
    msg = joint_state(header=header(stamp=stamp(sec=12, nanosec=34), frame_id='base'),
                      name=['left', 'right_wheel'], position=np.array([0.5, 1.5]),
                      velocity=np.array([2.5, -3.25]), effort=np.array([], dtype=float))
    reader = JointStateReader()
    for little in (True, False):
        data = bytes(typestore.serialize_cdr(msg, joint_state.__msgtype__,
                                             little_endian=little))
        t_ns, n_names, key, velocity = reader.read(data)
        assert (t_ns, n_names, velocity) == (12 * NS_PER_S + 34, 2, (2.5, -3.25))
        assert reader.names(key) == ['left', 'right_wheel']
    little_key = reader.read(bytes(typestore.serialize_cdr(msg, joint_state.__msgtype__)))[2]
    big_key = reader.read(bytes(typestore.serialize_cdr(msg, joint_state.__msgtype__,
                                                        little_endian=False)))[2]
    assert little_key != big_key  # the same names in another byte order are another layout


@pytest.mark.parametrize('data', [b'', b'\x00\x07\x00\x00' + bytes(40), b'\x00\x01\x00\x00',
                                  b'\x00\x01\x00\x00' + bytes(8) + b'\xff\xff\x00\x00'])
def test_joint_state_reader_refuses_what_it_cannot_read(data: bytes) -> None:
    with pytest.raises(WireFormatError):
        JointStateReader().read(data)


def test_joint_state_reader_refuses_truncated_messages() -> None:
    msg = JointState()
    msg.name = ['left', 'right']
    msg.velocity = [1.0, 2.0]
    data = serialize_message(msg)
    full = JointStateReader().read(data)
    assert full[3] == (1.0, 2.0)
    velocity_end = data.rindex(np.float64(2.0).tobytes()) + 8
    assert 4 <= len(data) - velocity_end <= 8  # then only the empty effort count (and padding)
    for cut in range(len(data)):
        if cut < velocity_end:  # a field the reader needs is cut: refused, every time
            with pytest.raises(WireFormatError):
                JointStateReader().read(data[:cut])
            continue
        try:  # only the trailing effort count is cut: the fields read are all there
            result = JointStateReader().read(data[:cut])
        except WireFormatError:
            continue
        assert result == full


@pytest.mark.parametrize('frames', [('odom', 'base_link'), ('', ''), ('o', 'b'),
                                    ('map_frame_x', 'robot/base_footprint'), ('ödom', 'bäse')])
def test_odometry_writer_round_trips_through_rclpy(frames: tuple[str, str]) -> None:
    writer = OdometryWriter(*frames)
    assert writer.agrees_with(deserialize_message, Odometry)
    rng = np.random.default_rng(3)
    for _ in range(20):
        pose_cov = rng.normal(size=36).tolist()
        twist_cov = rng.normal(size=36).tolist()
        x, y, qz, qw, vx, vy, wz = rng.normal(size=7).tolist()
        t_ns = int(rng.integers(0, 2**31 * NS_PER_S))
        msg = deserialize_message(writer.pack(t_ns, x, y, qz, qw, pose_cov, vx, vy, wz,
                                              twist_cov), Odometry)
        expected = Odometry()
        expected.header.stamp.sec, expected.header.stamp.nanosec = divmod(t_ns, NS_PER_S)
        expected.header.frame_id, expected.child_frame_id = frames
        expected.pose.pose.position.x, expected.pose.pose.position.y = x, y
        expected.pose.pose.orientation.z, expected.pose.pose.orientation.w = qz, qw
        expected.pose.covariance = np.array(pose_cov)
        expected.twist.twist.linear.x, expected.twist.twist.linear.y = vx, vy
        expected.twist.twist.angular.z = wz
        expected.twist.covariance = np.array(twist_cov)
        assert msg == expected


def test_odometry_writer_self_check_catches_a_wrong_layout() -> None:
    writer = OdometryWriter('odom', 'base_link')
    writer._doubles_at += 8  # what a layout mistake would look like
    assert not writer.agrees_with(deserialize_message, Odometry)
