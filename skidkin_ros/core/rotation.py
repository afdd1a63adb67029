"""Planar rotations as quaternions, shared by the node and the bag reader and writer."""

from __future__ import annotations

import math

__all__ = ['yaw_to_quaternion', 'quaternion_to_yaw']


def yaw_to_quaternion(yaw_rad: float) -> tuple[float, float, float, float]:
    """Return the (x, y, z, w) quaternion of a rotation about z."""
    half = 0.5 * float(yaw_rad)
    return 0.0, 0.0, math.sin(half), math.cos(half)


def quaternion_to_yaw(x: float, y: float, z: float, w: float) -> float:
    """Return the yaw (rad, in [-pi, pi]) of a quaternion; roll and pitch are ignored."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
