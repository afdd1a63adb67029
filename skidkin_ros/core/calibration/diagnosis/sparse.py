"""The sparse fallback's start: which library terms explain the residual, by STLSQ.

When no named extension explains the residual, a library extension (``sparse_correction``)
adds a linear combination of terms of the base twist and its rate (v, w, v|v|, ..., dv, dw:
:data:`skidkin_ros.core.kinematics.extensions.LIBRARY`). Which terms, and their start values,
come from sequentially thresholded least squares (STLSQ, as in SINDy) of each per-pose residual
component on the library: regress, drop the terms whose standardised coefficient is below the
threshold, repeat. Standardising makes one threshold mean the same for every term; the
threshold is a fraction of the residual's spread, so it does not depend on units. The terms
kept are then refitted on segments with the base model like any extension.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from skidkin_ros.core.calibration.diagnosis.options import DiagnosisOptions
from skidkin_ros.core.calibration.diagnosis.residuals import pose_residuals, PoseSamples
from skidkin_ros.core.calibration.engine import TwistSource
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.kinematics.sparse_library import (SPARSE_FEATURES, sparse_features,
                                                        SPARSE_OUTPUTS)

__all__ = ['stlsq', 'library_start']

# Start values stay inside the coefficients' bounds (+-10).
START_LIMIT = 9.9


def stlsq(features: np.ndarray, target: np.ndarray, threshold: float,
          iterations: int = 10) -> np.ndarray:
    """Sequentially thresholded least squares on standardised features; return coefficients.

    A term is dropped when its standardised coefficient is below ``threshold`` times the target's
    standard deviation (so the threshold is a fraction of the residual explained).
    """
    scale = features.std(axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    z = features / scale
    target_scale = max(float(target.std()), 1e-12)
    active = np.ones(z.shape[1], dtype=bool)
    coef = np.zeros(z.shape[1])
    for _ in range(iterations):
        if not active.any():
            break
        sol, *_ = np.linalg.lstsq(z[:, active], target, rcond=None)
        coef = np.zeros(z.shape[1])
        coef[active] = sol
        keep = np.abs(coef) >= threshold * target_scale
        if np.array_equal(keep, active):
            break
        active = keep
    coef[~active] = 0.0
    return coef / scale


def library_start(drives: Sequence[Drive], samples: PoseSamples, source: TwistSource,
                  options: DiagnosisOptions, drives_kept: np.ndarray | None,
                  threshold: float) -> tuple[dict[str, float], tuple[str, ...]]:
    """Return the start values and names of the library terms STLSQ keeps for each component.

    ``source``: the current model (its residual is regressed); ``drives_kept``: the indices of
    the drives whose poses may be used (a cross-validation fold's training drives; None: all).
    """
    residual, valid = pose_residuals(drives, samples, source, options)
    if drives_kept is not None:
        valid &= np.isin(samples.drive, drives_kept)
    features = sparse_features(samples.base_twist, samples.base_rate)[valid]
    values = {}
    terms = []
    for c, (out, _) in enumerate(SPARSE_OUTPUTS):
        coef = stlsq(features, residual[valid, c], threshold)
        for (feat, _), value in zip(SPARSE_FEATURES, coef):
            if value != 0.0:
                name = f'{out}_{feat}'
                values[name] = float(np.clip(value, -START_LIMIT, START_LIMIT))
                terms.append(name)
    return values, tuple(terms)
