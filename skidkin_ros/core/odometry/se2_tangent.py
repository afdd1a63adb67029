"""Exact derivatives of the SE(2) step and rollout (:mod:`~skidkin_ros.core.odometry.se2`).

Forward mode: every function takes the values the rollout computes plus their tangents, arrays
with a leading axis of P directions (one per fitted parameter: each direction contiguous, so each
operation is P plain array operations), and returns the tangents of its outputs. The fits of
augmented models use them for an exact Jacobian of the segment end-pose errors (instead of one
rollout per parameter and iteration for a finite difference).
"""

from __future__ import annotations

import numpy as np

from skidkin_ros.core.odometry.se2 import _sinc_terms, body_increment

__all__ = ['sinc_slopes', 'body_increment_tangent', 'compose_tangent', 'rollout_tangent']

# Below this rotation per step the slopes of sin(a)/a and (1 - cos a)/a come from their series.
_SLOPE_SERIES_RAD = 1e-2


def sinc_slopes(dtheta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return d/da of sin(a)/a and of (1 - cos a)/a, continuous through a = 0."""
    a = np.asarray(dtheta, dtype=float)
    small = np.abs(a) < _SLOPE_SERIES_RAD
    safe = np.where(small, 1.0, a)
    sin_t, cos_t = np.sin(safe), np.cos(safe)
    a2 = a * a
    d_sin = np.where(small, -a / 3.0 + a * a2 / 30.0, (safe * cos_t - sin_t) / safe ** 2)
    d_cos = np.where(small, 0.5 - a2 / 8.0 + a2 * a2 / 144.0,
                     (safe * sin_t - (1.0 - cos_t)) / safe ** 2)
    return d_sin, d_cos


def body_increment_tangent(v_x, v_y, omega, dt_s, d_v_x, d_v_y, d_omega
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tangents of :func:`~skidkin_ros.core.odometry.se2.body_increment` (dt_s fixed).

    ``v_x``, ``v_y``, ``omega``, ``dt_s``: (...); their tangents (P, ...).
    """
    dt = np.asarray(dt_s, dtype=float)
    dtheta = np.asarray(omega, dtype=float) * dt
    sin_a, cos_a = _sinc_terms(dtheta)
    d_sin, d_cos = sinc_slopes(dtheta)
    s, c = sin_a * dt, cos_a * dt
    dt2 = dt * dt
    slope_x = (v_x * d_sin - v_y * d_cos) * dt2
    slope_y = (v_x * d_cos + v_y * d_sin) * dt2
    return (d_v_x * s - d_v_y * c + slope_x * d_omega,
            d_v_x * c + d_v_y * s + slope_y * d_omega, d_omega * dt)


def compose_tangent(theta, dx, dy, d_x, d_y, d_theta, d_dx, d_dy, d_dtheta
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tangents of :func:`~skidkin_ros.core.odometry.se2.compose` (pose then body increment).

    Values (...), tangents (P, ...).
    """
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    return (d_x + cos_t * d_dx - sin_t * d_dy - (sin_t * dx + cos_t * dy) * d_theta,
            d_y + sin_t * d_dx + cos_t * d_dy + (cos_t * dx - sin_t * dy) * d_theta,
            d_theta + d_dtheta)


def rollout_tangent(v_x, v_y, omega, dt_s, d_v_x, d_v_y, d_omega
                    ) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    """Roll out from the origin; return the poses and what any window's derivative is made of.

    The poses are :func:`~skidkin_ros.core.odometry.se2.rollout_columns`' (to rounding).

    ``v_x``, ``v_y``, ``omega``, ``dt_s``: (N, L); their tangents (P, N, L). Returns the poses
    (x, y, yaw), each (N, L + 1), and three running sums (P, N, L + 1), 0 at the start:
    ``u_x``, ``u_y`` and ``w``. The move from pose a to pose b (b >= a) then has the tangents
    R(yaw_a)^T (u[b] - u[a] + J p_b (w[b] - w[a])) (position, J p = (-p_y, p_x)) and
    w[b] - w[a] (heading): each step's own change, turned into the world frame, plus the turn
    of the rest of the window about the step's end (p_b - p_i+1), split into a part summed
    here and one taken at the window's end. Steps before a turn the whole window and drop out.
    """
    dx, dy, dtheta = body_increment(v_x, v_y, omega, dt_s)
    dt = np.asarray(dt_s, dtype=float)
    count, length = np.shape(dtheta)
    poses = [np.zeros((count, length + 1)) for _ in range(3)]
    np.cumsum(dtheta, axis=1, out=poses[2][:, 1:])
    theta = poses[2][:, :-1]  # heading at the start of each step
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    np.cumsum(cos_t * dx - sin_t * dy, axis=1, out=poses[0][:, 1:])
    np.cumsum(sin_t * dx + cos_t * dy, axis=1, out=poses[1][:, 1:])
    # d (dx, dy) / d (v_x, v_y, omega) of each step, turned into the world frame: values only
    sin_a, cos_a = _sinc_terms(dtheta)
    d_sin, d_cos = sinc_slopes(dtheta)
    s, c = sin_a * dt, cos_a * dt
    dt2 = dt * dt
    slope_x = (v_x * d_sin - v_y * d_cos) * dt2
    slope_y = (v_x * d_cos + v_y * d_sin) * dt2
    m_xv, m_xy = cos_t * s - sin_t * c, -cos_t * c - sin_t * s
    m_yv, m_yy = sin_t * s + cos_t * c, cos_t * s - sin_t * c
    # the turn of the rest of the window about the step's end: -J p_i+1 dt d omega
    m_xw = cos_t * slope_x - sin_t * slope_y + poses[1][:, 1:] * dt
    m_yw = sin_t * slope_x + cos_t * slope_y - poses[0][:, 1:] * dt
    columns = np.shape(d_v_x)[0]
    sums = [np.zeros((columns, count, length + 1)) for _ in range(3)]
    np.cumsum(m_xv * d_v_x + m_xy * d_v_y + m_xw * d_omega, axis=-1, out=sums[0][..., 1:])
    np.cumsum(m_yv * d_v_x + m_yy * d_v_y + m_yw * d_omega, axis=-1, out=sums[1][..., 1:])
    np.cumsum(dt * d_omega, axis=-1, out=sums[2][..., 1:])
    return tuple(poses), tuple(sums)
