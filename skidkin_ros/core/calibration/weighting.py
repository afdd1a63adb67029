"""The iterated (feasible generalised least-squares) fit: the loss weighted by the noise model.

Why: the paper's loss l(k) = sum_i e_i^T Sigma^-1 e_i is a Mahalanobis distance, meant with the
covariance of the errors. With Sigma = identity (1 m weighs as much as 1 rad) on 2 m / 1 rad
segments, the position errors dominate and heading is under-fitted. The covariance
of a segment's end-pose error is what the calibrated noise model predicts for it
(:mod:`skidkin_ros.core.calibration.noise_fit`): it grows with the distance and the turning of
that segment and couples heading to position through the lever arm. So, as a recipe:

1. **Start.** The fixed-Sigma fit of :func:`skidkin_ros.core.calibration.fitting.fit_model`
   (multi-start, no trimming): the first residuals.
2. **Covariances.** Fit the noise model on the training residuals (maximum likelihood) and take
   each segment's predicted covariance Sigma_i (:func:`noise_covariances`, the one call into the
   noise model); W_i = L_i^-1 with L_i L_i^T = Sigma_i.
3. **Refit** from the current parameters with the per-segment whitening W_i (the one engine).
4. **Repeat** 2-3 until no parameter moves by more than ``tolerance`` relative to its typical
   magnitude, at most ``max_iterations`` times (the noise rates are fitted on at most
   ``max_noise_segments`` segments, evenly spread: four rates need no more, and the cost grows
   with the count).
5. **Trim** (the project's rule, :func:`skidkin_ros.core.calibration.engine.trim_mask`) on the
   whitened distances e_i^T Sigma_i^-1 e_i, at every iteration: the refit of step 3 uses the
   kept segments, and the next noise fit too.

The standard errors then come from the whitened Jacobian, as for the fixed-Sigma fit. The scale
of Sigma does not move the minimum, only the relative weight of the segments and of x, y and
heading, so the coverage factor of the published noise is left out here.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import logging
import math
import time
from typing import Sequence

import numpy as np

from skidkin_ros.core.calibration.engine import trim_mask
from skidkin_ros.core.calibration.fitting import (assess_fit, fit_model, FitOptions, FitResult,
                                                  parameter_scales, segment_errors, solve_model)
from skidkin_ros.core.calibration.noise_fit import (fit_noise_model, segment_covariances,
                                                    segment_motion)
from skidkin_ros.core.calibration.segments import SegmentSet
from skidkin_ros.core.kinematics.models import get_model, MODEL_NAMES
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.errors import DataError, ParameterError

__all__ = ['WEIGHTINGS', 'IterationOptions', 'noise_covariances', 'whitening_matrices',
           'fit_model_iterated', 'fit_models_weighted']

LOG = logging.getLogger(__name__)
WEIGHTINGS = ('iterated', 'fixed')


@dataclass(frozen=True)
class IterationOptions:
    """Bounds of the iteration (module docstring, step 4)."""

    max_iterations: int = 8
    tolerance: float = 1e-3
    max_noise_segments: int = 300

    def __post_init__(self) -> None:
        if self.max_iterations < 1:
            raise ParameterError(f'max_iterations must be >= 1, got {self.max_iterations!r}')
        if not (self.tolerance > 0 and math.isfinite(self.tolerance)):
            raise ParameterError(f'tolerance must be > 0, got {self.tolerance!r}')


def noise_covariances(name: str, values: dict[str, float], geometry: Geometry,
                      fit_segments: SegmentSet, fit_errors: np.ndarray,
                      segments: SegmentSet | None = None,
                      max_fit_segments: int | None = None) -> np.ndarray:
    """Fit the model's noise on ``fit_errors`` and return the covariances (N, 3, 3) of segments.

    The one place the fit and the model choice call the noise model: maximum-likelihood rates
    on the errors of ``fit_segments`` (noise_fit.fit_noise_model), then each segment's predicted
    end-pose covariance (noise_fit.segment_covariances); ``segments`` defaults to the fit's own.
    ``max_fit_segments``: fit the rates on at most that many of them, evenly spread (a few
    rates need a few hundred segments; the cost of the fit grows with their number).

    The noise here leaves out the part per second of motion (the published noise,
    noise_fit.calibrate_noise, has it): weights and the model choice need a stable relative
    weighting of the segments, often on a few dozen of them, and the extra terms let a model
    that drifts explain its drift as noise. On a 150 s Warthog-like drive with 11 held-out
    segments, ideal_dd (13 deg/m of heading error against 0.45 for edd_symmetric) came within
    two standard errors of the best held-out likelihood with them, and was chosen.
    """
    target = fit_segments if segments is None else segments
    if max_fit_segments is not None and len(fit_segments) > max_fit_segments:
        pick = np.unique(np.linspace(0, len(fit_segments) - 1, max_fit_segments).round()
                         .astype(int))
        fit_segments, fit_errors = fit_segments.subset(pick), fit_errors[pick]
    motion = segment_motion(name, values, geometry, fit_segments)
    noise = fit_noise_model(fit_errors, motion, time=False)
    if target is not fit_segments:
        motion = segment_motion(name, values, geometry, target)
    return segment_covariances(noise, motion)


def whitening_matrices(cov: np.ndarray) -> np.ndarray:
    """Return W (N, 3, 3) with W^T W = cov^-1 (the inverse Cholesky factor)."""
    return np.linalg.inv(np.linalg.cholesky(cov))


def _settle(name: str, geometry: Geometry, segments: SegmentSet, options: FitOptions,
            k: np.ndarray, iterations: IterationOptions):
    """Run steps 2-5 from ``k``: (solution, kept mask, iterations, settled).

    The trimming rule is applied at every iteration to the current whitened distances, and the
    noise is fitted on the segments the previous iteration kept: one loop, not two.
    """
    model = get_model(name)
    typical = parameter_scales(model, geometry)
    kept = np.ones(len(segments), bool)
    sol = None
    for count in range(1, iterations.max_iterations + 1):
        errors = segment_errors(model, k, geometry, segments)
        fit_idx = np.nonzero(kept)[0]
        weight = whitening_matrices(noise_covariances(
            name, model.mapping(k), geometry, segments.subset(fit_idx), errors[fit_idx],
            segments, max_fit_segments=iterations.max_noise_segments))
        if options.trim:
            kept = trim_mask(errors, weight, options.trim_chi2, options.trim_max_fraction)
        used = segments if kept.all() else segments.subset(np.nonzero(kept)[0])
        sol = solve_model(model, geometry, used, options, k, weight=weight[kept])
        step = float(np.max(np.abs(sol.x - k) / typical))
        k = sol.x
        if step < iterations.tolerance:
            return sol, kept, count, True
    return sol, kept, iterations.max_iterations, False


def fit_model_iterated(name: str, geometry: Geometry, segments: SegmentSet,
                       options: FitOptions | None = None,
                       iterations: IterationOptions | None = None) -> FitResult:
    """Fit one model with the noise model's covariances as weights (module docstring)."""
    options = options or FitOptions()
    iterations = iterations or IterationOptions()
    model = get_model(name)
    start = fit_model(name, geometry, segments, replace(options, trim=False))
    if not model.params:
        return start
    tic = time.perf_counter()
    k = model.vector(start.values, geometry)
    try:
        sol, kept, count, settled = _settle(name, geometry, segments, options, k, iterations)
    except (DataError, np.linalg.LinAlgError) as err:
        LOG.warning('%s: iterated weighting not possible (%s); kept the fixed-Sigma fit',
                    name, err)
        return fit_model(name, geometry, segments, options)
    used = segments if kept.all() else segments.subset(np.nonzero(kept)[0])
    result = assess_fit(model, geometry, used, options, sol, start.starts, int((~kept).sum()),
                        kept, start.seconds + time.perf_counter() - tic, weighting='iterated')
    if not settled:
        result = replace(result, warnings=result.warnings + (
            f'{name}: the iterated weighting had not settled after {count} iterations (the '
            'last one is used)',))
    return replace(result, iterations=count)


def fit_models_weighted(geometry: Geometry, segments: SegmentSet,
                        options: FitOptions | None = None,
                        models: Sequence[str] = MODEL_NAMES, weighting: str = 'iterated',
                        iterations: IterationOptions | None = None) -> dict[str, FitResult]:
    """Fit every requested model, iterated (default) or with the options' fixed Sigma."""
    if weighting not in WEIGHTINGS:
        raise ParameterError(f'weighting must be one of {WEIGHTINGS}, got {weighting!r}')
    options = options or FitOptions()
    results = {}
    for name in models:
        if weighting == 'fixed':
            result = fit_model(name, geometry, segments, options)
        else:
            result = fit_model_iterated(name, geometry, segments, options, iterations)
        LOG.info('fitted %s (%s) on %d segments in %.2f s (cost %.4g, valid %s)', name,
                 weighting, result.segments_used, result.seconds, result.cost, result.valid)
        results[name] = result
    return results
