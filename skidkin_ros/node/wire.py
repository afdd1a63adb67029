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
aligned to its size counted from the end of that header. Anything else (an unknown encapsulation,
a message that does not parse) makes :meth:`JointStateReader.read` raise :class:`WireFormatError`,
and the node falls back to rclpy's own deserialization. :class:`OdometryWriter` checks itself
once against rclpy when it is built and is not used if they disagree.
"""

from __future__ import annotations

import struct
from typing import Any, Sequence

__all__ = ['WireFormatError', 'JointStateReader', 'OdometryWriter', 'encapsulation_prefix']

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


class JointStateReader:
    """Read the stamp, the joint-name list and the velocities of a serialized JointState.

    ``read`` returns ``(stamp_ns, n_names, names_key, velocity)``: ``names_key`` is the byte
    order and the raw bytes of the name list, so a driver that repeats its names (they all do)
    is recognised by a byte comparison, and :meth:`names` decodes them only when the key
    changes. ``velocity`` is a tuple of floats (possibly shorter than the names: the caller
    checks).
    """

    def __init__(self) -> None:
        self._last_key = b''  # the names_key of the last message read

    def read(self, data: bytes) -> tuple[int, int, bytes, tuple[float, ...]]:
        """Return (stamp_ns, number of names, names_key, velocities)."""
        order = encapsulation_prefix(data)
        try:
            sec, nanosec = struct.unpack_from(order + 'iI', data, HEADER_BYTES)
            offset = self._skip_string(data, order, 8)  # header.frame_id
            names_start = offset = _aligned(offset, 4)
            key = self._last_key
            # The same name list as last time (the usual case): the same bytes, the same key.
            if key[:1] == order.encode() and data.startswith(key[1:], HEADER_BYTES + offset):
                offset += len(key) - 1
                (n_names,) = struct.unpack_from(order + 'I', key, 1)
            else:
                (n_names,) = struct.unpack_from(order + 'I', data, HEADER_BYTES + offset)
                offset += 4
                for _ in range(n_names):
                    offset = self._skip_string(data, order, _aligned(offset, 4))
                key = order.encode() + data[HEADER_BYTES + names_start:HEADER_BYTES + offset]
                self._last_key = key
            offset, _ = self._doubles(data, order, offset, keep=False)  # position
            _, velocity = self._doubles(data, order, offset, keep=True)
        except struct.error as err:
            raise WireFormatError(f'JointState does not parse as plain CDR: {err}') from err
        return sec * 1_000_000_000 + nanosec, n_names, key, velocity

    @staticmethod
    def names(names_key: bytes) -> list[str]:
        """Decode the joint names of a ``names_key`` returned by :meth:`read`."""
        order = names_key[:1].decode('ascii')
        names_key = names_key[1:]
        try:
            (count,) = struct.unpack_from(order + 'I', names_key, 0)
            offset = 4
            out = []
            for _ in range(count):
                offset = _aligned(offset, 4)
                (length,) = struct.unpack_from(order + 'I', names_key, offset)
                raw = names_key[offset + 4:offset + 4 + length]
                if length == 0 or len(raw) != length or raw[-1] != 0:
                    raise WireFormatError('a joint name is not a terminated CDR string')
                out.append(raw[:-1].decode('utf-8'))
                offset += 4 + length
        except (struct.error, UnicodeDecodeError) as err:
            raise WireFormatError(f'JointState names do not parse: {err}') from err
        return out

    @staticmethod
    def _skip_string(data: bytes, order: str, offset: int) -> int:
        """Return the body offset just after the CDR string at body offset ``offset``."""
        (length,) = struct.unpack_from(order + 'I', data, HEADER_BYTES + offset)
        end = offset + 4 + length
        if HEADER_BYTES + end > len(data):
            raise struct.error(f'a string of {length} bytes runs past the end of the data')
        return end

    @staticmethod
    def _doubles(data: bytes, order: str, offset: int, keep: bool
                 ) -> tuple[int, tuple[float, ...]]:
        """Read a sequence<double> at body offset ``offset``; return (end offset, values)."""
        offset = _aligned(offset, 4)
        (count,) = struct.unpack_from(order + 'I', data, HEADER_BYTES + offset)
        offset += 4
        if count == 0:
            return offset, ()
        offset = _aligned(offset, 8)
        end = offset + 8 * count
        if HEADER_BYTES + end > len(data):
            raise struct.error(f'a sequence of {count} doubles runs past the end of the data')
        values = (struct.unpack_from(f'{order}{count}d', data, HEADER_BYTES + offset)
                  if keep else ())
        return end, values


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
        _STAMP.pack_into(buf, HEADER_BYTES, *divmod(t_ns, 1_000_000_000))
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
