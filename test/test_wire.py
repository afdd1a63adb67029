"""The node's CDR codecs against two independent serializers: rclpy's and rosbags'."""

from __future__ import annotations

import collections
import math
import random
import struct
import sys

from nav_msgs.msg import Odometry
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import get_typestore, Stores
from sensor_msgs.msg import JointState
from skidkin_ros.node import wire
from skidkin_ros.node.wire import (JointStateFields, JointStateReader, OdometryWriter,
                                   WireFormatError)

NS_PER_S = 1_000_000_000


def _random_joint_state(rng: random.Random) -> JointState:
    msg = JointState()
    msg.header.stamp.sec = rng.randrange(-2**31, 2**31)
    msg.header.stamp.nanosec = rng.randrange(0, 2**32)
    msg.header.frame_id = 'f' * rng.randrange(0, 9)
    n = rng.randrange(0, 6)
    msg.name = [''.join(rng.choice('abcé_') for _ in range(rng.randrange(0, 12)))
                for _ in range(n)]
    values = (-9.5, 0.0, -0.0, math.nan, math.inf, 1e-310)
    for field in ('position', 'velocity', 'effort'):
        count = rng.choice((0, n, max(n - 1, 0), n + 2))
        setattr(msg, field, [rng.choice(values) if rng.random() < 0.1 else rng.uniform(-9, 9)
                             for _ in range(count)])
    return msg


def _doubles_bytes(values) -> bytes:
    """Return values as bytes: a comparison that is exact for NaN, -0.0 and denormals."""
    return struct.pack(f'<{len(values)}d', *values)


def _rclpy_fields(data: bytes) -> JointStateFields | None:
    """Return what rclpy's deserializer gives for data, None if it refuses it."""
    try:
        msg = deserialize_message(data, JointState)
    except RuntimeError:  # rclpy's RMWError
        return None
    stamp = msg.header.stamp
    return JointStateFields(stamp.sec * NS_PER_S + stamp.nanosec, tuple(msg.name),
                            tuple(msg.position), tuple(msg.velocity))


class Differential:
    """Feed byte strings to the reader and to rclpy; the reader must agree or refuse."""

    def __init__(self) -> None:
        self.reader = JointStateReader()  # one reader: its name-list cache is exercised
        self.outcomes: collections.Counter[str] = collections.Counter()

    def check(self, data: bytes) -> str:
        expected = _rclpy_fields(data)
        for reader in (self.reader, JointStateReader()):
            try:
                got = reader.read(data)
            except WireFormatError:
                got = None
            if got is not None:
                assert expected is not None, f'the reader accepted what rclpy refuses: {data!r}'
                assert (got.stamp_ns, got.names) == (expected.stamp_ns, expected.names), data
                assert _doubles_bytes(got.position) == _doubles_bytes(expected.position), data
                assert _doubles_bytes(got.velocity) == _doubles_bytes(expected.velocity), data
                assert type(got.position) is tuple and type(got.velocity) is tuple
        outcome = ('both read' if got is not None else
                   'both refuse' if expected is None else 'left to rclpy')
        self.outcomes[outcome] += 1
        return outcome


def _build(order: str, frame: bytes, names: list[bytes], position, velocity, effort,
           encapsulation: bytes | None = None, pad: bytes = b'\x00', double_align: int = 8
           ) -> tuple[bytes, dict[str, int]]:
    """Serialize a JointState by hand (strings given raw); return it and where each count is.

    ``double_align`` 4 gives the XCDR2 layout (with encapsulation 0x0007).
    """
    body = bytearray()
    at: dict[str, int] = {}

    def align(n: int) -> None:
        body.extend(pad * (-len(body) % n))

    def count(name: str, value: int) -> None:
        align(4)
        at[name] = 4 + len(body)
        body.extend(struct.pack(order + 'I', value))

    body.extend(struct.pack(order + 'iI', 12, 34))
    count('frame_id', len(frame))
    body.extend(frame)
    count('names', len(names))
    for i, raw in enumerate(names):
        count(f'name{i}', len(raw))
        body.extend(raw)
    for field, values in (('position', position), ('velocity', velocity), ('effort', effort)):
        count(field, len(values))
        if values:
            align(double_align)
            body.extend(struct.pack(f'{order}{len(values)}d', *values))
    head = encapsulation or (b'\x00\x01\x00\x00' if order == '<' else b'\x00\x00\x00\x00')
    return head + bytes(body), at


def _two_joints(**changes) -> tuple[bytes, dict[str, int]]:
    """Return the issue's valid message: two joints with positions, velocities and efforts."""
    fields = {'order': '<', 'frame': b'base\x00', 'names': [b'left\x00', b'right\x00'],
              'position': [0.25, 0.5], 'velocity': [1.5, -2.0], 'effort': [7.0, 8.0]}
    fields.update(changes)
    return _build(**fields)


def _with_uint32(data: bytes, offset: int, value: int) -> bytes:
    out = bytearray(data)
    struct.pack_into('<I', out, offset, value)
    return bytes(out)


def test_reader_matches_rclpy_on_random_valid_messages() -> None:
    rng = random.Random(7)
    diff = Differential()
    for _ in range(300):
        assert diff.check(serialize_message(_random_joint_state(rng))) == 'both read'


def test_reader_reads_big_and_little_endian_cdr_from_rosbags() -> None:
    typestore = get_typestore(Stores.ROS2_JAZZY)
    joint_state = typestore.types['sensor_msgs/msg/JointState']
    header = typestore.types['std_msgs/msg/Header']
    stamp = typestore.types['builtin_interfaces/msg/Time']
    msg = joint_state(header=header(stamp=stamp(sec=12, nanosec=34), frame_id='base'),
                      name=['left', 'right_wheel'], position=np.array([0.5, 1.5]),
                      velocity=np.array([2.5, -3.25]), effort=np.array([], dtype=float))
    diff = Differential()
    for little in (True, False, True):  # the same names in another byte order are not cached
        data = bytes(typestore.serialize_cdr(msg, joint_state.__msgtype__,
                                             little_endian=little))
        assert diff.check(data) == 'both read'
        assert diff.reader.read(data) == (12 * NS_PER_S + 34, ('left', 'right_wheel'),
                                          (0.5, 1.5), (2.5, -3.25))


def test_reader_refuses_what_rclpy_refuses_in_the_issue_cases() -> None:
    """Red-team case: a wrong position count read effort as velocity; a cut effort passed."""
    data, at = _two_joints()
    diff = Differential()
    assert diff.check(data) == 'both read'
    five_positions = _with_uint32(data, at['position'], 5)
    assert _rclpy_fields(five_positions) is None
    with pytest.raises(WireFormatError):
        JointStateReader().read(five_positions)
    for cut in range(at['effort'], len(data)):  # the effort count or its values cut
        assert diff.check(data[:cut]) == 'both refuse'
    assert diff.check(data + bytes(13)) == 'both read'  # rclpy ignores bytes after the effort


def test_reader_leaves_to_rclpy_what_rclpy_decodes_its_own_way() -> None:
    """Red-team case: names rclpy accepts but decodes by its own rules, other encodings."""
    odd_names = [b'\xff\xfeleg\x00', b'le\x00ft\x00', b'left', b'', b'\xed\xa0\x80\x00']
    diff = Differential()
    for odd in odd_names:
        data, _ = _two_joints(names=[odd, b'right\x00'])
        assert diff.check(data) == 'left to rclpy', odd
    data, _ = _two_joints(encapsulation=b'\x00\x03\x00\x00')  # PL_CDR_LE (a final type)
    assert diff.check(data) == 'left to rclpy'
    data, _ = _two_joints(encapsulation=b'\x00\x07\x00\x00', double_align=4)  # XCDR2
    assert diff.check(data) == 'left to rclpy'
    data, _ = _two_joints(encapsulation=b'\x00\x01\x07\x03', pad=b'\xa5')  # options, padding
    assert diff.check(data) == 'both read'
    data, _ = _two_joints(frame=b'')  # an empty header.frame_id of length 0 (rclpy takes it)
    assert diff.check(data) == 'both read'


def _hostile_names(n_bytes: int) -> bytes:
    """Red-team case: n_names = 2**32 - 1, then n_bytes of zeros (each a name of length 0)."""
    data, at = _two_joints()
    return _with_uint32(data[:at['names'] + 4], at['names'], 2**32 - 1) + bytes(n_bytes)


def _lines_run(read, data: bytes) -> int:
    """Return how many lines of node/wire.py ``read(data)`` executes (the work it does)."""
    lines = 0

    def trace(frame, event, arg):
        nonlocal lines
        if frame.f_code.co_filename != wire.__file__:
            return None
        if event == 'line':
            lines += 1
        return trace

    previous = sys.gettrace()
    sys.settrace(trace)
    try:
        read(data)
    except WireFormatError:
        pass
    finally:
        sys.settrace(previous)
    return lines


def test_long_name_lists_are_left_to_rclpy() -> None:
    """Past MAX_FAST_NAMES names rclpy's C loop is the faster reader; up to it, the fast path."""
    diff = Differential()
    for n, outcome in ((wire.MAX_FAST_NAMES, 'both read'),
                       (wire.MAX_FAST_NAMES + 1, 'left to rclpy')):
        names = [f'joint_{i}'.encode() + b'\x00' for i in range(n)]
        data, _ = _two_joints(names=names, velocity=[0.5] * n)
        assert diff.check(data) == outcome


def test_forged_name_count_is_refused_before_any_name_is_read() -> None:
    hostile = _hostile_names(1_000_000)
    valid, _ = _two_joints()
    # The work: fewer lines than reading a valid two-joint message (the old reader looped over
    # the zeros, one name of length 0 per 4 bytes: 250 000 iterations per MB).
    assert _lines_run(JointStateReader().read, hostile) < _lines_run(JointStateReader().read,
                                                                     valid)
    with pytest.raises(WireFormatError, match='claims 4294967295 joint names but only 1000000 '
                                              'bytes follow'):
        JointStateReader().read(hostile)
    assert _rclpy_fields(hostile) is None


def _mutations(rng: random.Random, data: bytes, at: dict[str, int]):
    """Yield mutated copies of a message: cuts, forged counts, flipped and random bytes."""
    for cut in rng.sample(range(len(data)), min(len(data), 12)):
        yield data[:cut]
    size = len(data)
    for name, offset in at.items():
        value = struct.unpack_from('<I', data, offset)[0]
        for forged in {0, 1, 2, 5, value - 1, value + 1, value + 2, (size - offset) // 4,
                       (size - offset) // 8, 2**31, 2**32 - 1}:
            yield _with_uint32(data, offset, forged % 2**32)
    for _ in range(20):
        out = bytearray(data)
        for _ in range(rng.randrange(1, 4)):
            out[rng.randrange(4, size)] = rng.randrange(256)
        yield bytes(out)
    for _ in range(5):
        yield data[:4] + rng.randbytes(rng.randrange(0, 2 * size))
    yield data + rng.randbytes(rng.randrange(1, 16))
    insert = rng.randrange(4, size)
    yield data[:insert] + bytes(rng.randrange(1, 8)) + data[insert:]
    yield data[:insert] + data[insert + rng.randrange(1, 8):]


def _random_built(rng: random.Random) -> tuple[bytes, dict[str, int]]:
    """Return a hand-built JointState: either byte order, odd names now and then, any lengths."""
    n = rng.randrange(0, 5)
    names = []
    for _ in range(n):
        raw = ''.join(rng.choice('ab_é') for _ in range(rng.randrange(0, 9))).encode() + b'\x00'
        if rng.random() < 0.1:
            raw = rng.choice((b'', raw[:-1], b'\xff' + raw, b'a\x00' + raw))
        names.append(raw)
    seqs = [[rng.uniform(-5, 5) for _ in range(rng.choice((0, n, n + 1)))] for _ in range(3)]
    return _build(rng.choice('<>'), b'odom\x00'[:rng.randrange(0, 6)], names, *seqs)


def _fuzz(seed: int, messages: int) -> collections.Counter[str]:
    rng = random.Random(seed)
    diff = Differential()
    for _ in range(messages):
        data, at = _random_built(rng)
        diff.check(data)
        for mutated in _mutations(rng, data, at):
            diff.check(mutated)
    return diff.outcomes


def test_reader_agrees_with_rclpy_or_refuses_on_mutated_messages() -> None:
    """Differential: on valid, cut, forged and random bytes the reader equals rclpy or refuses."""
    outcomes = _fuzz(seed=12, messages=40)
    # Not vacuous: every outcome occurs (the reader reads, both refuse, rclpy alone reads).
    assert min(outcomes['both read'], outcomes['both refuse'], outcomes['left to rclpy']) > 20


@pytest.mark.heavy
def test_reader_agrees_with_rclpy_or_refuses_on_many_mutated_messages() -> None:
    outcomes = _fuzz(seed=1212, messages=2000)
    assert min(outcomes.values()) > 1000 and len(outcomes) == 3


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
