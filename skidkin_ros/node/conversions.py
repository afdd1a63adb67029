"""Conversions between ROS messages and the plain numbers the core works with.

Kept free of node state so each conversion can be tested on its own. Times are integer
nanoseconds. How wheel speeds are read from a JointState (joint lookup, side speed) is not here
but in :mod:`skidkin_ros.core.odometry.wheels`, shared with the bag reader.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

from builtin_interfaces.msg import Time
import numpy as np
from skidkin_ros.core.rotation import quaternion_to_yaw
from skidkin_ros.core.timeunits import NS_PER_S

__all__ = [
    'stamp_to_ns',
    'ns_to_stamp',
    'planar_pose_from_msg',
    'planar_covariance_from_msg',
]


def stamp_to_ns(stamp: Any) -> int:
    """Return a builtin_interfaces/Time as integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(t_ns: int) -> Time:
    """Return integer nanoseconds as a builtin_interfaces/Time (t_ns >= 0)."""
    sec, nanosec = divmod(int(t_ns), NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


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


def planar_covariance_from_msg(covariance: Sequence[float]) -> np.ndarray:
    """Return the (x, y, yaw) block of a 6x6 row-major covariance, as given.

    It is checked (finite, bounded, positive semi-definite) where it is used:
    :meth:`skidkin_ros.core.odometry.odometer.Odometer.reset`.
    """
    full = np.asarray(covariance, dtype=float).reshape(6, 6)
    return full[np.ix_([0, 1, 5], [0, 1, 5])]
