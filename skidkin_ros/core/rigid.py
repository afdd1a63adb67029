"""Rigid 3D transforms as 4x4 matrices: change of frame, planar reduction, scaling in time.

The lidar ground truth (:mod:`skidkin_ros.adapters.lidar_gt`) needs three things of kiss-icp's
poses, and the benches the same three: a lidar motion seen from base_link (E T E^-1, E the
extrinsic), the planar pose (x, y, yaw) with the tilt that says how planar it is, and a motion
scaled in time, exp(f log T), for a constant-velocity guess over a different interval. The
exponential and the left Jacobian of SO(3) are written out (Rodrigues, with the small-angle
series) so the guesses kiss-icp is given stay exactly what they were; scipy gives the logarithm.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ['change_frame', 'planar_pose', 'planar_poses', 'se3_exp_scaled', 'se3_log',
           'se3_power']


def change_frame(transform: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """Return ``frame @ transform @ frame^-1``: a motion of a sensor seen from the body.

    With ``frame`` = E = T_base_sensor and ``transform`` a sensor pose in the first sensor frame,
    this is the body pose in the first body frame.
    """
    return frame @ transform @ np.linalg.inv(frame)


def planar_pose(transform: np.ndarray) -> tuple[float, float, float, float]:
    """Return (x, y, yaw, tilt) of a 4x4 pose; tilt is the angle of its z axis from vertical."""
    yaw = math.atan2(transform[1, 0], transform[0, 0])
    tilt = math.acos(max(-1.0, min(1.0, float(transform[2, 2]))))
    return float(transform[0, 3]), float(transform[1, 3]), yaw, tilt


def planar_poses(transforms: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """Return (N, 4) x, y, yaw, tilt of sensor poses (N, 4, 4) seen from the body (``frame``)."""
    return np.array([planar_pose(change_frame(t, frame)) for t in transforms],
                    dtype=float).reshape(-1, 4)


def _skew(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _so3_exp(w: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(w))
    k = _skew(w)
    if theta < 1e-9:
        return np.eye(3) + k
    return (np.eye(3) + math.sin(theta) / theta * k
            + (1.0 - math.cos(theta)) / theta ** 2 * k @ k)


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(w))
    k = _skew(w)
    if theta < 1e-6:
        return np.eye(3) + 0.5 * k + k @ k / 6.0
    return (np.eye(3) + (1.0 - math.cos(theta)) / theta ** 2 * k
            + (theta - math.sin(theta)) / theta ** 3 * k @ k)


def se3_log(transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (rho, rotvec) of a rigid 4x4 transform: its twist, exp([rho, rotvec]) = T."""
    from scipy.spatial.transform import Rotation

    rotvec = Rotation.from_matrix(transform[:3, :3]).as_rotvec()
    rho = np.linalg.solve(_left_jacobian(rotvec), transform[:3, 3])
    return rho, rotvec


def se3_exp_scaled(rho: np.ndarray, rotvec: np.ndarray, fraction: float) -> np.ndarray:
    """Return exp(fraction [rho, rotvec]) as a rigid 4x4 transform."""
    scaled = fraction * rotvec
    out = np.eye(4)
    out[:3, :3] = _so3_exp(scaled)
    out[:3, 3] = _left_jacobian(scaled) @ (fraction * rho)
    return out


def se3_power(transform: np.ndarray, fraction: float) -> np.ndarray:
    """Return exp(fraction log(T)) of a rigid 4x4 transform: the same motion, scaled in time."""
    return se3_exp_scaled(*se3_log(transform), fraction)
