"""Planar rotations as quaternions, shared by the node and the bag reader and writer."""

from __future__ import annotations

import math

__all__ = ['yaw_to_quaternion', 'quaternion_to_yaw']


def yaw_to_quaternion(yaw_rad: float) -> tuple[float, float, float, float]:
    """Return the (x, y, z, w) quaternion of a rotation about z."""
    half = 0.5 * float(yaw_rad)
    return 0.0, 0.0, math.sin(half), math.cos(half)


def quaternion_to_yaw(x: float, y: float, z: float, w: float) -> float:
    """Return the yaw (rad, in [-pi, pi]) of a quaternion; roll and pitch are ignored.

    The formula holds for unit quaternions: one off by more than 1e-6 in squared norm is
    normalized first (scaled by 0.5 it read a 90 degree turn as 18 degrees); a zero or
    non-finite one has no yaw: NaN, which every reader refuses as a non-finite pose.
    """
    norm2 = x * x + y * y + z * z + w * w
    if not abs(norm2 - 1.0) <= 1e-6:
        if not (math.isfinite(norm2) and norm2 > 1e-18):
            return math.nan
        scale = 1.0 / math.sqrt(norm2)
        x, y, z, w = x * scale, y * scale, z * scale, w * scale
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
