"""Conversions between ROS messages and the plain numbers the core works with.

Kept free of node state so each conversion can be tested on its own. Times are integer
nanoseconds; a malformed message raises :class:`MalformedMessageError`, a JointState without one
of the configured wheel joints raises :class:`MissingJointError` (fault row N20).
"""

from __future__ import annotations

import array
import math
from typing import Any, Sequence

from builtin_interfaces.msg import Time
import numpy as np
from skidkin_ros.core.rotation import quaternion_to_yaw

__all__ = [
    'MalformedMessageError',
    'MissingJointError',
    'stamp_to_ns',
    'ns_to_stamp',
    'side_speed',
    'check_velocity_count',
    'joint_indices',
    'speeds_at',
    'planar_pose_from_msg',
    'planar_covariance_from_msg',
    'plain_value',
]

NS_PER_S = 1_000_000_000


class MalformedMessageError(ValueError):
    """A message whose fields contradict each other (e.g. fewer velocities than names)."""


class MissingJointError(ValueError):
    """A JointState that lacks one of the configured wheel joints."""


def stamp_to_ns(stamp: Any) -> int:
    """Return a builtin_interfaces/Time as integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(t_ns: int) -> Time:
    """Return integer nanoseconds as a builtin_interfaces/Time (t_ns >= 0)."""
    sec, nanosec = divmod(int(t_ns), NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


def side_speed(values: Sequence[float]) -> float:
    """Return the mean of one side's wheel speeds (rad/s).

    Identical values return that value unchanged, so a single-wheel reading survives the mean
    bit for bit (the node then matches an offline prediction exactly).
    """
    first = float(values[0])
    if all(float(v) == first for v in values):
        return first
    return math.fsum(float(v) for v in values) / len(values)


def joint_indices(names: Sequence[str], left_joints: Sequence[str],
                  right_joints: Sequence[str]) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Return where the left and right wheel joints are in a JointState's ``name`` list.

    Raises MissingJointError when a configured joint is absent. Drivers send the same name list
    every time, so the node looks the indices up once per distinct list.
    """
    index = {name: i for i, name in enumerate(names)}
    missing = [joint for joint in (*left_joints, *right_joints) if joint not in index]
    if missing:
        raise MissingJointError(
            f'JointState lacks wheel joint(s) {missing} (it has {list(names)}); check '
            'left_wheel_joints / right_wheel_joints')
    return (tuple(index[joint] for joint in left_joints),
            tuple(index[joint] for joint in right_joints))


def check_velocity_count(n_names: int, n_velocities: int) -> None:
    """Raise MalformedMessageError when a JointState has fewer velocities than names."""
    if n_velocities < n_names:
        raise MalformedMessageError(
            f'JointState has {n_names} names but only {n_velocities} velocities; expected '
            'one velocity (rad/s) per joint name')


def speeds_at(velocity: Sequence[float], left: Sequence[int],
              right: Sequence[int]) -> tuple[float, float]:
    """Return (omega_left, omega_right) in rad/s: each the mean of its joints' velocities."""
    return side_speed([velocity[i] for i in left]), side_speed([velocity[i] for i in right])


def planar_pose_from_msg(pose: Any) -> tuple[float, float, float]:
    """Return (x, y, yaw) of a geometry_msgs/Pose; ValueError when any field is not finite."""
    values = (pose.position.x, pose.position.y, pose.position.z, pose.orientation.x,
              pose.orientation.y, pose.orientation.z, pose.orientation.w)
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f'pose has a non-finite field: position ({values[0]}, {values[1]}, '
                         f'{values[2]}), orientation {values[3:]}; expected finite numbers')
    q = np.array(values[3:])
    norm = float(np.linalg.norm(q))
    if norm < 1e-9:
        raise ValueError('pose orientation is a zero quaternion; expected a unit quaternion')
    return float(values[0]), float(values[1]), quaternion_to_yaw(*(q / norm))


def planar_covariance_from_msg(covariance: Sequence[float]) -> np.ndarray | None:
    """Return the (x, y, yaw) block of a 6x6 row-major covariance, or None if unusable."""
    full = np.asarray(covariance, dtype=float).reshape(6, 6)
    block = full[np.ix_([0, 1, 5], [0, 1, 5])]
    if not np.all(np.isfinite(block)) or np.any(np.diag(block) < 0.0):
        return None
    return 0.5 * (block + block.T)


def plain_value(value: Any) -> Any:
    """Return a parameter value with arrays as lists (rclpy hands out array.array)."""
    if isinstance(value, (array.array, tuple, np.ndarray)):
        return list(value)
    return value
