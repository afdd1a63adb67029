"""Exact derivatives of the SE(2) step and rollout (:mod:`~skidkin_ros.core.odometry.se2`).

Forward mode: every function takes the values the rollout computes plus their tangents, arrays
with a leading axis of P directions (one per fitted parameter: each direction contiguous, so each
operation is P plain array operations), and returns the tangents of its outputs. The fits of
augmented models use them for an exact Jacobian of the segment end-pose errors (instead of one
rollout per parameter and iteration for a finite difference).
"""

from __future__ import annotations

import numpy as np

from skidkin_ros.core.odometry.se2 import _sinc_terms, sin_cos
from skidkin_ros.core.scratch import scratch

__all__ = ['sinc_slopes', 'body_increment_tangent', 'compose_tangent',
           'window_tangents']

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


def _sinc_values_and_slopes(dtheta: np.ndarray, exact: bool = True) -> tuple[np.ndarray, ...]:
    """Return sin(a)/a, (1 - cos a)/a and their slopes, from one sin and one cos of a."""
    a = np.asarray(dtheta, dtype=float)
    small = np.abs(a) < _SLOPE_SERIES_RAD
    safe = np.where(small, 1.0, a)
    sin_t, cos_t = sin_cos(safe, exact)
    a2 = a * a
    sinc = np.where(small, 1.0 - a2 / 6.0 + a2 * a2 / 120.0, sin_t / safe)
    cosc = np.where(small, a / 2.0 - a * a2 / 24.0 + a * a2 * a2 / 720.0, (1.0 - cos_t) / safe)
    d_sin = np.where(small, -a / 3.0 + a * a2 / 30.0, (cos_t - sinc) / safe)
    d_cos = np.where(small, 0.5 - a2 / 8.0 + a2 * a2 / 144.0, (sin_t - cosc) / safe)
    return sinc, cosc, d_sin, d_cos


def window_tangents(v_x, v_y, omega, dt_s, d_v_x, d_v_y, d_omega, a: np.ndarray,
                    b: np.ndarray, exact: bool = True
                    ) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    """Roll out from the origin; return the poses and what each window's derivative is made of.

    ``v_x``, ``v_y``, ``omega``, ``dt_s``: (N, L), one step between stamps i and i + 1 (the
    last of each row unused); their tangents (P, N, L). ``a``, ``b``: flat stamp indices of
    each window (b >= a, same row). Returns the poses (x, y, yaw) at every stamp, each flat
    (N * L,) (:func:`~skidkin_ros.core.odometry.se2.rollout_columns`' to rounding), and three
    sums over each window's steps, each (P, S): ``u_x``, ``u_y`` and ``w``. The move from
    stamp a to stamp b then has the tangents R(yaw_a)^T (u + J p_b w) (position, J p =
    (-p_y, p_x)) and w (heading): each step's own change, turned into the world frame, plus
    the turn of the rest of the window about the step's end (p_b - p_i+1), split into a part
    summed here and one taken at the window's end. Steps before a turn the whole window and
    drop out. ``exact=False``: the cheaper trigonometry of
    :func:`~skidkin_ros.core.odometry.se2.sin_cos` (to rounding).
    """
    dt = np.array(dt_s, dtype=float)
    dt[:, -1] = 0.0  # no step after the last stamp
    dtheta = np.asarray(omega, dtype=float) * dt
    sinc, cosc, d_sin, d_cos = _sinc_values_and_slopes(dtheta, exact)
    s, c = sinc * dt, cosc * dt
    dx, dy = v_x * s - v_y * c, v_x * c + v_y * s
    count, length = np.shape(dtheta)
    poses = [np.zeros((count, length)) for _ in range(3)]
    np.cumsum(dtheta[:, :-1], axis=1, out=poses[2][:, 1:])
    sin_t, cos_t = sin_cos(poses[2], exact)  # heading at the start of each step
    np.cumsum((cos_t * dx - sin_t * dy)[:, :-1], axis=1, out=poses[0][:, 1:])
    np.cumsum((sin_t * dx + cos_t * dy)[:, :-1], axis=1, out=poses[1][:, 1:])
    # d (dx, dy) / d (v_x, v_y, omega) of each step, turned into the world frame: values only
    dt2 = dt * dt
    slope_x = (v_x * d_sin - v_y * d_cos) * dt2
    slope_y = (v_x * d_cos + v_y * d_sin) * dt2
    m_xv, m_xy = cos_t * s - sin_t * c, -cos_t * c - sin_t * s
    m_yv, m_yy = sin_t * s + cos_t * c, cos_t * s - sin_t * c
    # the turn of the rest of the window about the step's end: -J p_i+1 dt d omega
    after_x = np.empty_like(dt)
    after_y = np.empty_like(dt)
    after_x[:, :-1], after_y[:, :-1] = poses[0][:, 1:], poses[1][:, 1:]
    after_x[:, -1] = after_y[:, -1] = 0.0
    m_xw = cos_t * slope_x - sin_t * slope_y + after_y * dt
    m_yw = sin_t * slope_x + cos_t * slope_y - after_x * dt
    columns = np.shape(d_v_x)[0]
    # window sums: one reduction over [a, b) each (the odd entries span the gaps: unused)
    bounds = np.empty(2 * len(a), dtype=np.int64)
    bounds[0::2], bounds[1::2] = a, b
    empty = (b <= a)
    step, term = scratch('step', np.shape(d_v_x)), scratch('term', np.shape(d_v_x))
    sums = []
    for row in ((m_xv, m_xy, m_xw), (m_yv, m_yy, m_yw), (None, None, dt)):
        np.multiply(row[2], d_omega, out=step)
        for factor, tangent in zip(row[:2], (d_v_x, d_v_y)):
            if factor is not None:
                step += np.multiply(factor, tangent, out=term)
        flat = step.reshape(columns, count * length)
        total = (np.add.reduceat(flat, bounds, axis=1)[:, 0::2] if len(a)
                 else np.zeros((columns, 0)))
        total[:, empty] = 0.0
        sums.append(total)
    return tuple(p.reshape(count * length) for p in poses), tuple(sums)
