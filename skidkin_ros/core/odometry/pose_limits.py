"""Pose and covariance limits of the odometry, and the checks of a pose set from outside.

A pose or covariance set from outside (``~/set_pose``, a restart of a prediction) is checked here
before the odometer takes it: from beyond these limits the next step could not stay finite (or
exact), and the odometry would never be published again.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

__all__ = ['POSE_LIMIT_M', 'YAW_RESOLUTION_RAD', 'YAW_LIMIT_RAD', 'VARIANCE_LIMIT', 'check_pose',
           'check_covariance']

# A pose set from outside is refused beyond this (m): a step from 1e308 m cannot stay finite, and
# no odometry frame is a million kilometres wide.
POSE_LIMIT_M = 1e9
# An unwrapped yaw grows with every turn, so no physical bound fits it (3 rad/s for ten years is
# 1e9 rad); the honest limit is where float64 stops resolving the angle: beyond YAW_LIMIT_RAD
# (about 4.5e9 rad, 7e8 turns) two neighbouring floats are more than YAW_RESOLUTION_RAD apart.
YAW_RESOLUTION_RAD = 1e-6
YAW_LIMIT_RAD = YAW_RESOLUTION_RAD / float(np.finfo(float).eps)
# Largest variance (m^2, rad^2) a set covariance may hold: beyond it, propagation overflows.
VARIANCE_LIMIT = 1e12


def check_pose(pose: Sequence[float]) -> tuple[float, float, float]:
    """Return (x, y, yaw) as floats, or raise ValueError for a pose the odometry cannot hold.

    x and y must be finite and within ``POSE_LIMIT_M``, yaw finite and within ``YAW_LIMIT_RAD``:
    from further out, the next step could not stay finite (or exact).
    """
    x, y, yaw = (float(v) for v in pose)
    if not (all(math.isfinite(v) and abs(v) <= POSE_LIMIT_M for v in (x, y))
            and math.isfinite(yaw) and abs(yaw) <= YAW_LIMIT_RAD):
        raise ValueError(f'pose (x {x:g} m, y {y:g} m, yaw {yaw:g} rad) is not finite or beyond '
                         f'{POSE_LIMIT_M:g} m (x, y) or {YAW_LIMIT_RAD:.3g} rad (yaw); expected '
                         'finite values within them')
    return x, y, yaw


def check_covariance(covariance: np.ndarray) -> np.ndarray:
    """Return a 3 x 3 (x, y, yaw) covariance made symmetric, or raise ValueError.

    It must be finite, positive semi-definite, with variances up to ``VARIANCE_LIMIT``: a larger
    one overflows when propagated, and the odometry would never be published again.
    """
    block = np.asarray(covariance, dtype=float).reshape(3, 3)
    if not np.all(np.isfinite(block)):
        raise ValueError('covariance has a non-finite value; expected finite variances')
    if np.abs(block).max() > VARIANCE_LIMIT:
        raise ValueError(f'covariance holds {np.abs(block).max():g}, beyond {VARIANCE_LIMIT:g} '
                         '(m^2, rad^2); give variances within it')
    block = 0.5 * (block + block.T)
    if np.linalg.eigvalsh(block).min() < -1e-9 * max(1.0, float(np.abs(block).max())):
        raise ValueError('covariance (x, y, yaw block) is not positive semi-definite; expected '
                         'non-negative variances and consistent correlations')
    return block
