"""JointState and Odometry in their serialized (CDR) form, for the node's per-sample path.

At 1 kHz on one core, rclpy's conversions between Python message objects and the wire dominate
what the node itself computes: building and serializing an Odometry with its two 36-element
covariances costs about 30 µs and deserializing a four-joint JointState about 16 µs, against
roughly 2 µs to pack or unpack the few fields the node uses with :mod:`struct`. The node
therefore subscribes to ``joint_states`` and publishes ``odom`` in serialized form (rclpy's
``raw=True`` subscriptions and ``Publisher.publish(bytes)``); the topic types on the graph are
unchanged.

Both codecs follow the plain CDR encoding (XCDR1) every ROS 2 middleware uses for ROS messages:
a 4-byte encapsulation header (byte 1 says big or little endian), then the fields in order, each
aligned to its size counted from the end of that header.

The reader is the node's door for data from any publisher on the graph, so it holds to one rule:
what it returns is exactly what rclpy's deserializer returns for the same bytes, and what it does
not return it refuses with :class:`WireFormatError`, after which the node hands the bytes to rclpy
(which decides, and may refuse them too). rclpy's deserializer (Fast CDR through
rosidl_typesupport_fastrtps_c, found by experiment, ``test/test_wire.py`` keeps checking it)
refuses a message when any string or sequence runs past the end of the data, the effort array
included; it accepts bytes after the last field, any padding contents, any encapsulation options,
strings of length 0 or without their NUL, and names that are not UTF-8 (decoded with
replacement characters). The reader refuses everything rclpy refuses and, of the rest, leaves to
rclpy what it would have to imitate rather than read: encapsulations other than plain CDR and
names that are not NUL-terminated UTF-8. Every count is checked against the bytes left before
anything is read: the work is bounded by the size of the message, never by a forged count.

:class:`OdometryWriter` checks itself once against rclpy when it is built and is not used if they
disagree.
"""

from __future__ import annotations

import struct
from typing import Any, NamedTuple, Sequence

from skidkin_ros.core.timeunits import NS_PER_S

__all__ = ['WireFormatError', 'JointStateFields', 'JointStateReader', 'OdometryWriter',
           'encapsulation_prefix']

HEADER_BYTES = 4  # encapsulation: 0x00, 0x00 (big endian) or 0x01 (little endian), options
_PLAIN_CDR = {b'\x00\x00': '>', b'\x00\x01': '<'}
_ZERO_PAD = bytes(8)
_STAMP = struct.Struct('<iI')
_BODY = struct.Struct('<85d')  # Odometry after its two strings: 7 + 36 + 6 + 36 doubles


class WireFormatError(ValueError):
    """Serialized data this module does not read (the caller falls back to rclpy)."""


def encapsulation_prefix(data: bytes) -> str:
    """Return the struct byte-order prefix of plain CDR data; WireFormatError otherwise."""
    try:
        return _PLAIN_CDR[bytes(data[:2])]
    except KeyError:
        raise WireFormatError(f'encapsulation {bytes(data[:2]).hex()} is not plain CDR '
                              '(expected 0000 or 0001)') from None


def _aligned(offset: int, size: int) -> int:
    """Return the body offset rounded up to a multiple of size."""
    return (offset + size - 1) // size * size


class JointStateFields(NamedTuple):
    """The fields of a sensor_msgs/JointState the node uses, as rclpy would give them.

    ``stamp_ns``: ``header.stamp`` in integer nanoseconds (sec * 1e9 + nanosec);
    ``names``: the joint names; ``position`` and ``velocity``: the two sequences as tuples of
    floats. Each sequence may be empty or of any length (the message type allows it): the
    caller checks them against the names. (A named tuple: one is made per message.)
    """

    stamp_ns: int
    names: tuple[str, ...]
    position: tuple[float, ...]
    velocity: tuple[float, ...]


_new_fields = tuple.__new__
# Per byte order (encapsulation byte 1): unpackers of the stamp and of a uint32, and the struct
# prefix for sequences of doubles.
_LAYOUTS = ((struct.Struct('>iI').unpack_from, struct.Struct('>I').unpack_from, '>'),
            (struct.Struct('<iI').unpack_from, struct.Struct('<I').unpack_from, '<'))
_FRAME_ID_AT = HEADER_BYTES + 8  # the header.frame_id length, after header.stamp
_MIN_NAME_BYTES = 4  # a CDR string is at least its uint32 length (rclpy accepts length 0)
# Longer name lists are left to rclpy, whose C loop decodes them about twice as fast as this
# module's Python one: beyond any robot's joint count, a message costs no more than rclpy's own.
MAX_FAST_NAMES = 256


class JointStateReader:
    """Read a serialized JointState exactly as far as rclpy's deserializer does, or refuse it.

    :meth:`read` walks the whole message, as rclpy (Fast CDR) does: the header, every name,
    then position, velocity and effort, each count checked against the bytes left before
    anything is read (a forged count is refused at once), and refuses with
    :class:`WireFormatError` any message rclpy refuses (a sequence or a string that runs past
    the end of the data). Bytes after the effort array are ignored, as rclpy ignores them.

    The fast path reads only what it can read without guessing; it refuses, so that the caller
    hands the message to rclpy, what rclpy would accept but decode its own way: names that are
    not NUL-terminated UTF-8 (rclpy cuts them at the first NUL and replaces invalid bytes),
    encapsulations other than plain CDR (XCDR2, parameter lists); and lists of more than
    :data:`MAX_FAST_NAMES` names, which rclpy decodes faster. A driver repeats its name
    list: the list's bytes are kept and, when the next message holds the same bytes, the names
    are not decoded again.
    """

    def __init__(self) -> None:
        # The last name list read: (byte order, its serialized bytes, the names). One attribute,
        # replaced whole, so a reader shared by threads never pairs bytes and names wrongly.
        self._last_names: tuple[int, bytes, tuple[str, ...]] = (-1, b'', ())

    def read(self, data: bytes) -> JointStateFields:
        """Return the fields of a serialized JointState; WireFormatError if not read here."""
        size = len(data)
        if size < _FRAME_ID_AT + 4 or data[0] or data[1] > 1:
            encapsulation_prefix(data)  # raises, naming the encapsulation, when that is the cause
            raise WireFormatError(f'JointState of {size} bytes ends inside its header')
        little = data[1]
        stamp, uint32, order = _LAYOUTS[little]
        try:
            sec, nanosec = stamp(data, HEADER_BYTES)
            (length,) = uint32(data, _FRAME_ID_AT)
            offset = _FRAME_ID_AT + 4 + length
            if offset > size:
                raise WireFormatError(f'header.frame_id of {length} bytes runs past the end of '
                                      f'the data ({size} bytes)')
            offset = _aligned(offset, 4)  # the name count: 4-aligned (the header is 4 bytes)
            known_order, known, names = self._last_names
            if little == known_order and data.startswith(known, offset):
                offset += len(known)  # the name list of the last message (the usual case)
            else:
                names, end = _names(data, uint32, offset)
                self._last_names = (little, data[offset:end], names)
                offset = end
            position, offset = _doubles(data, uint32, order, offset, 'position', True)
            velocity, offset = _doubles(data, uint32, order, offset, 'velocity', True)
            _doubles(data, uint32, order, offset, 'effort', False)
        except struct.error as err:  # a count or a length cut by the end of the data
            raise WireFormatError(f'JointState ends inside a field: {err}') from err
        return _new_fields(JointStateFields, (sec * NS_PER_S + nanosec, names, position,
                                              velocity))


def _names(data: bytes, uint32: Any, offset: int) -> tuple[tuple[str, ...], int]:
    """Decode the name sequence at ``offset``; return the names and the offset after them."""
    size = len(data)
    (count,) = uint32(data, offset)
    offset += 4
    if count > (size - offset) // _MIN_NAME_BYTES:
        raise WireFormatError(f'JointState claims {count} joint names but only {size - offset} '
                              f'bytes follow (a name takes at least {_MIN_NAME_BYTES})')
    if count > MAX_FAST_NAMES:
        raise WireFormatError(f'JointState lists {count} joint names, more than the fast reader '
                              f'takes ({MAX_FAST_NAMES}): left to rclpy')
    names = []
    for i in range(count):
        offset = _aligned(offset, 4)
        (length,) = uint32(data, offset)
        start = offset + 4
        offset = start + length
        if offset > size:
            raise WireFormatError(f'joint name {i} of {length} bytes runs past the end of the '
                                  f'data ({size} bytes)')
        raw = data[start:offset - 1]
        if not length or data[offset - 1] or b'\x00' in raw:
            raise WireFormatError(f'joint name {i} is not a NUL-terminated string: left to rclpy')
        try:
            names.append(raw.decode('utf-8'))
        except UnicodeDecodeError as err:
            raise WireFormatError(f'joint name {i} is not UTF-8 ({err}): left to rclpy') from None
    return tuple(names), offset


def _doubles(data: bytes, uint32: Any, order: str, offset: int, field: str, keep: bool
             ) -> tuple[tuple[float, ...], int]:
    """Read a sequence<double> at ``offset``; return its values (if ``keep``) and its end."""
    offset = _aligned(offset, 4)
    (count,) = uint32(data, offset)
    offset += 4
    if not count:  # no alignment padding for an empty sequence (as rclpy reads it)
        return (), offset
    offset = ((offset + 3) & ~7) + 4  # 8-aligned counted from the end of the 4-byte header
    end = offset + 8 * count
    if end > len(data):
        raise WireFormatError(f'JointState {field} claims {count} values but only '
                              f'{max(len(data) - offset, 0)} bytes follow')
    return (struct.unpack_from(f'{order}{count}d', data, offset) if keep else ()), end


class OdometryWriter:
    """Pack a nav_msgs/Odometry (little-endian plain CDR) from the numbers the node has.

    The frame ids are fixed when the writer is built (the node builds a new one when they
    change). :meth:`pack` writes the stamp, the pose (position x, y; orientation z, w), the twist
    (linear x, y; angular z) and the two row-major 6 x 6 covariances; every other field is zero,
    as in the node's message.
    """

    def __init__(self, frame_id: str, child_frame_id: str) -> None:
        self.frame_id = frame_id
        self.child_frame_id = child_frame_id
        head = bytearray()
        offset = 8  # header.stamp
        for text in (frame_id, child_frame_id):
            encoded = text.encode('utf-8') + b'\x00'
            aligned = _aligned(offset, 4)
            head += _ZERO_PAD[:aligned - offset] + struct.pack('<I', len(encoded)) + encoded
            offset = aligned + 4 + len(encoded)
        doubles_at = _aligned(offset, 8)
        head += _ZERO_PAD[:doubles_at - offset]
        self._buffer = bytearray(b'\x00\x01\x00\x00' + bytes(8) + head + bytes(85 * 8))
        self._doubles_at = HEADER_BYTES + doubles_at

    def pack(self, t_ns: int, x: float, y: float, qz: float, qw: float,
             pose_covariance: Sequence[float], vx: float, vy: float, wz: float,
             twist_covariance: Sequence[float]) -> bytes:
        """Return the serialized message (t_ns: integer ns, 0 <= t_ns < 2**31 s)."""
        buf = self._buffer
        _STAMP.pack_into(buf, HEADER_BYTES, *divmod(t_ns, NS_PER_S))
        # pose.pose: position x y z, orientation x y z w; then pose.covariance; twist.twist:
        # linear x y z, angular x y z; then twist.covariance.
        _BODY.pack_into(buf, self._doubles_at, x, y, 0.0, 0.0, 0.0, qz, qw, *pose_covariance,
                        vx, vy, 0.0, 0.0, 0.0, wz, *twist_covariance)
        return bytes(buf)

    def agrees_with(self, deserialize: Any, msg_type: Any) -> bool:
        """Tell whether ``deserialize(pack(...), msg_type)`` gives back what was packed."""
        pose_cov = [0.5 + i for i in range(36)]
        twist_cov = [-1.25 * i for i in range(36)]
        try:
            data = self.pack(1_234_567_890_123_456_789, 1.5, -2.25, 0.6, 0.8, pose_cov, 0.75,
                             -0.125, 0.3125, twist_cov)
            msg = deserialize(data, msg_type)
        except Exception:  # noqa: B902 - any failure means: do not use this writer
            return False
        pose, twist = msg.pose.pose, msg.twist.twist
        return (msg.header.stamp.sec == 1_234_567_890 and msg.header.stamp.nanosec == 123_456_789
                and msg.header.frame_id == self.frame_id
                and msg.child_frame_id == self.child_frame_id
                and (pose.position.x, pose.position.y, pose.position.z) == (1.5, -2.25, 0.0)
                and (pose.orientation.x, pose.orientation.y, pose.orientation.z,
                     pose.orientation.w) == (0.0, 0.0, 0.6, 0.8)
                and list(msg.pose.covariance) == pose_cov
                and (twist.linear.x, twist.linear.y, twist.linear.z) == (0.75, -0.125, 0.0)
                and (twist.angular.x, twist.angular.y, twist.angular.z) == (0.0, 0.0, 0.3125)
                and list(msg.twist.covariance) == twist_cov)
