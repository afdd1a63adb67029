"""One step of the pose's sensitivity to the parameters, on floats, per wheel sample.

S' = F S + G dt d(twist)/dk (:mod:`skidkin_ros.core.odometry.uncertainty` derives it), for the
p columns of S as 3-tuples: :func:`propagate_sensitivity` with any d(twist)/dk,
:func:`propagate_linear` fused for a model linear in the wheel speeds (the same operations in
the same order, bit for bit), and :func:`add_weighted_outer` to read S Sigma_k S^T in the
covariance's eigenbasis. :class:`~skidkin_ros.core.odometry.propagation.PoseCovariancePropagator`
calls them; plain floats because per sample a small numpy product costs more than its arithmetic.
"""

from __future__ import annotations

import math
from typing import Sequence

from skidkin_ros.core.odometry.integrator import step_scalar

__all__ = ['step_frame', 'propagate_sensitivity', 'propagate_linear', 'add_weighted_outer']


def step_frame(yaw: float, w: float, dt_s: float, dx: float, dy: float
               ) -> tuple[float, float, float, float, float]:
    """Return (cos, sin of the mid-step heading, F[0, 2], F[1, 2], dt / 2) of one step."""
    cos_t = math.cos(yaw)
    sin_t = math.sin(yaw)
    mid = yaw + 0.5 * w * dt_s
    a = -sin_t * dx - cos_t * dy  # F[0, 2]
    b = cos_t * dx - sin_t * dy   # F[1, 2]
    return math.cos(mid), math.sin(mid), a, b, 0.5 * dt_s


def propagate_sensitivity(sens: Sequence[tuple[float, float, float]],
                          jacobian: Sequence[tuple[float, float, float]], yaw: float, vx: float,
                          vy: float, w: float, dt_s: float) -> list[tuple[float, float, float]]:
    """One step of S' = F S + G d(increment)/dk (uncertainty module docstring), on floats.

    The increment's derivative is taken to second order in the step: a speed change acts along
    the mid-step heading, and a yaw-rate change turns the step by dw dt / 2.
    """
    _, _, _, dx, dy = step_scalar(0.0, 0.0, yaw, vx, vy, w, dt_s)
    cos_m, sin_m, a, b, half = step_frame(yaw, w, dt_s, dx, dy)
    out = []
    for (sx, sy, syaw), (dvx, dvy, dw) in zip(sens, jacobian):
        out.append((sx + a * syaw + dt_s * (cos_m * dvx - sin_m * dvy) + half * dw * a,
                    sy + b * syaw + dt_s * (sin_m * dvx + cos_m * dvy) + half * dw * b,
                    syaw + dt_s * dw))
    return out


def propagate_linear(sens: Sequence[tuple[float, float, float]],
                     rows: Sequence[Sequence[float]], yaw: float, w: float, dt_s: float,
                     vx: float, vy: float, dx: float, dy: float
                     ) -> list[tuple[float, float, float]]:
    """:func:`propagate_sensitivity` with d(twist)/dk_j = M_j twist (a linear model), fused.

    The same operations in the same order as :meth:`ParameterUncertainty.twist_jacobian`
    followed by :func:`propagate_sensitivity` (bit for bit), without the intermediate list;
    (dx, dy) is the step's body-frame increment, which the pose step computed already.
    """
    cos_m, sin_m, a, b, half = step_frame(yaw, w, dt_s, dx, dy)
    out = []
    append = out.append
    for (sx, sy, syaw), (m0, m1, m2, m3, m4, m5, m6, m7, m8) in zip(sens, rows):
        dvx = m0 * vx + m1 * vy + m2 * w
        dvy = m3 * vx + m4 * vy + m5 * w
        dw = m6 * vx + m7 * vy + m8 * w
        append((sx + a * syaw + dt_s * (cos_m * dvx - sin_m * dvy) + half * dw * a,
                sy + b * syaw + dt_s * (sin_m * dvx + cos_m * dvy) + half * dw * b,
                syaw + dt_s * dw))
    return out


def add_weighted_outer(upper: Sequence[float], sens: Sequence[tuple[float, float, float]],
                       weights: Sequence[float]) -> tuple[float, ...]:
    """Return ``upper`` + the upper triangle of sum_l weights_l t_l t_l^T (T = S V, on floats)."""
    c00 = c01 = c02 = c11 = c12 = c22 = 0.0
    for (tx, ty, tyaw), lam in zip(sens, weights):
        ux = lam * tx
        uy = lam * ty
        c00 += ux * tx
        c01 += ux * ty
        c02 += ux * tyaw
        c11 += uy * ty
        c12 += uy * tyaw
        c22 += lam * tyaw * tyaw
    p00, p01, p02, p11, p12, p22 = upper
    return p00 + c00, p01 + c01, p02 + c02, p11 + c11, p12 + c12, p22 + c22
