"""The quality of one lidar registration: inlier fraction, residual and degeneracy.

One job: measuring a registered frame against the previous frame's map points (see
:func:`registration_quality`; :mod:`skidkin_ros.adapters.lidar_gt` describes the measures).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ['registration_quality']

# Points this far above the lowest tenth of a scan count as structure (not ground).
_GROUND_CLEARANCE_M = 0.3


def _world(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    return points @ pose[:3, :3].T + pose[:3, 3]


def registration_quality(source: np.ndarray, pose: np.ndarray, reference: Any,
                         voxel_m: float, n_sample: int) -> tuple[float, float, float]:
    """Return (inlier fraction, median residual m, degeneracy) of one registered frame.

    ``source``: the points kiss-icp registered (deskewed, sensor frame); ``reference``: a
    cKDTree of the previous frame's map points in the world frame. A sampled point is an inlier
    when the reference has a point within one voxel; the residual is the median distance of the
    inliers (what kiss-icp's point-to-point ICP minimises). Degeneracy: the smallest eigenvalue
    of the mean of u u^T over the sampled points, u the horizontal unit direction of a point
    standing above the ground (0.3 m over the lowest tenth of the points) and 0 for a ground
    point: 0 when nothing constrains the planar position (an open field, only the ground) or
    when all structure lies along one line (a corridor), up to 0.5 for structure all around.
    """
    if n_sample <= 0 or source.shape[0] == 0:
        return math.nan, math.nan, math.nan
    step = max(1, source.shape[0] // n_sample)
    local = source[::step][:n_sample]
    dist, _ = reference.query(_world(local, pose), k=1, distance_upper_bound=voxel_m)
    near = np.isfinite(dist)
    inlier_fraction = float(np.count_nonzero(near)) / local.shape[0]
    residual = float(np.median(dist[near])) if np.any(near) else math.nan
    structure = local[local[:, 2] > np.percentile(local[:, 2], 10) + _GROUND_CLEARANCE_M]
    horizontal = np.hypot(structure[:, 0], structure[:, 1])
    structure = structure[horizontal > 1e-6]
    if structure.shape[0] == 0:
        return inlier_fraction, residual, 0.0
    u = structure[:, :2] / np.hypot(structure[:, 0], structure[:, 1])[:, None]
    degeneracy = float(np.linalg.eigvalsh(u.T @ u / local.shape[0])[0])
    return inlier_fraction, residual, degeneracy
