"""Exact derivatives of the SE(2) step and rollout (:mod:`~skidkin_ros.core.odometry.se2`).

Forward mode: every function takes the values the rollout computes plus their tangents, arrays
with a trailing axis of P directions (one per fitted parameter), and returns the tangents of its
outputs. The fits of augmented models use them for an analytic Jacobian of the segment end-pose
errors (instead of one rollout per parameter and iteration for a finite difference).
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

    ``v_x``, ``v_y``, ``omega``, ``dt_s``: (...); their tangents (..., P).
    """
    dt = np.asarray(dt_s, dtype=float)
    dtheta = np.asarray(omega, dtype=float) * dt
    sin_a, cos_a = _sinc_terms(dtheta)
    d_sin, d_cos = sinc_slopes(dtheta)
    s, c = (sin_a * dt)[..., None], (cos_a * dt)[..., None]
    dt2 = dt * dt
    slope_x = ((v_x * d_sin - v_y * d_cos) * dt2)[..., None]
    slope_y = ((v_x * d_cos + v_y * d_sin) * dt2)[..., None]
    d_dx = d_v_x * s - d_v_y * c + slope_x * d_omega
    d_dy = d_v_x * c + d_v_y * s + slope_y * d_omega
    return d_dx, d_dy, d_omega * dt[..., None]


def compose_tangent(theta, dx, dy, d_x, d_y, d_theta, d_dx, d_dy, d_dtheta
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tangents of :func:`~skidkin_ros.core.odometry.se2.compose` (pose then body increment)."""
    cos_t, sin_t = np.cos(theta)[..., None], np.sin(theta)[..., None]
    dx, dy = np.asarray(dx)[..., None], np.asarray(dy)[..., None]
    return (d_x + cos_t * d_dx - sin_t * d_dy - (sin_t * dx + cos_t * dy) * d_theta,
            d_y + sin_t * d_dx + cos_t * d_dy + (cos_t * dx - sin_t * dy) * d_theta,
            d_theta + d_dtheta)


def rollout_tangent(v_x, v_y, omega, dt_s, d_twist: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tangents of :func:`~skidkin_ros.core.odometry.se2.rollout_columns` from a fixed start.

    ``v_x``, ``v_y``, ``omega``, ``dt_s``: (N, L); ``d_twist``: (N, L, 3, P). Returns the
    tangents of x, y, yaw at every pose (N, L + 1, P), 0 at the start.
    """
    dx, dy, dtheta = body_increment(v_x, v_y, omega, dt_s)
    d_dx, d_dy, d_dtheta = body_increment_tangent(v_x, v_y, omega, dt_s, d_twist[..., 0, :],
                                                  d_twist[..., 1, :], d_twist[..., 2, :])
    count, length = np.shape(dtheta)
    theta = np.cumsum(dtheta, axis=1) - dtheta  # heading at the start of each step (start 0)
    d_theta = np.cumsum(d_dtheta, axis=1) - d_dtheta
    zero = np.zeros((count, length, d_twist.shape[-1]))
    step_x, step_y, _ = compose_tangent(theta, dx, dy, zero, zero, d_theta, d_dx, d_dy, zero)
    out = []
    for step in (step_x, step_y, d_dtheta):
        total = np.zeros((count, length + 1, d_twist.shape[-1]))
        np.cumsum(step, axis=1, out=total[:, 1:])
        out.append(total)
    return out[0], out[1], out[2]
