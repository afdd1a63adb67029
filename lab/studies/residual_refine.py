"""Refine the residual model's coefficients on the end-pose errors of whole segments (a study).

Measured and not used by ``skidkin diagnose`` (docs/residual-model.md: it lowers the training
segments' error and costs held-out error); kept in the lab, tested, for a study with more
segments per coefficient: ``refine_coefficients(predictor, base, geometry, state, options)``
on a diagnosis state that holds a residual model.

The regression (:mod:`.regression`) fits the residual model's coefficients C on per-pose
velocity residuals, differentiated from the noisy ground truth; the odometry integrates the
correction into poses, and the paper's criterion is the end-pose error of whole segments. This
step moves C toward that criterion, regularised toward the velocity fit by its posterior:

1. **Prior.** The velocity fit's coefficients m and their (inflated) posterior covariance S, for
   the coefficients in use (the level's terms; the others stay 0).
2. **Data.** The whitened end-pose errors r(C) of the (kept) training segments, from the
   :class:`~skidkin_ros.core.calibration.predictor.SegmentPredictor` (the same rollout and exact
   Jacobian as every fit of the diagnosis); their variance s^2 per whitened unit is estimated
   from the velocity fit's segment errors, r^T r / (3 N - p).
3. **MAP.** Minimise r^T r / s^2 + (C - m)^T S^-1 (C - m) by damped Gauss-Newton: the correction
   is linear in C per sample, so a few iterations suffice; a step is kept only if it lowers the
   objective (else the damping grows); coefficients stay inside their bounds.
4. **Covariance.** The Gauss-Newton posterior (J^T J / s^2 + S^-1)^-1 at the result, inflated by
   (1 + rho) / (1 - rho), rho the lag-one autocorrelation of the segment errors along each drive
   (neighbouring segments share ground-truth noise), as the regression inflates its own.

The gains on each component are refined afterwards as before; whether the correction is kept at
all stays the selection's decision on held-out segments.
"""

from __future__ import annotations

import numpy as np

from skidkin_ros.core.calibration.diagnosis.options import DiagnosisOptions
from skidkin_ros.core.calibration.diagnosis.regression import (autocorrelation, block_folds,
                                                               COEF_LIMIT)
from skidkin_ros.core.calibration.diagnosis.state import held_out_loss, ModelState
from skidkin_ros.core.calibration.engine import whiten, whitened_residuals
from skidkin_ros.core.calibration.predictor import SegmentPredictor
from skidkin_ros.core.kinematics import residual
from skidkin_ros.core.kinematics.extensions import get_extension
from skidkin_ros.core.kinematics.specs import Geometry

__all__ = ['MIN_FOLD_SEGMENTS', 'PRIOR_WEIGHTS', 'REFINE_ITERATIONS', 'refine_at',
           'refine_coefficients']

# Gauss-Newton iterations (each one Jacobian and at least one rollout).
REFINE_ITERATIONS = 4
# Scales of the prior precision S^-1 tried (1: the velocity fit's posterior as it is), the
# velocity fit alone being the other choice; cross-validated on the segments.
PRIOR_WEIGHTS = (0.3, 1.0, 3.0)
# Fewest segments a cross-validation half may have (fewer: no refinement).
MIN_FOLD_SEGMENTS = 10


def _regression(state: ModelState) -> str | None:
    """Return the state's regression extension (the residual model), if it has one."""
    return next((n for n in state.extensions if get_extension(n).regression), None)


def _prior_precision(cov: np.ndarray) -> np.ndarray:
    """Return S^-1 of a positive semi-definite S (eigenvalues floored at 1e-12 of the largest)."""
    cov = 0.5 * (cov + cov.T)
    eig, vec = np.linalg.eigh(cov)
    floor = max(float(eig.max(initial=0.0)), 1e-300) * 1e-12
    return (vec / np.maximum(eig, floor)) @ vec.T


def refine_coefficients(predictor: SegmentPredictor, base_name: str, geometry: Geometry,
                        state: ModelState, options: DiagnosisOptions,
                        keep: np.ndarray | None = None) -> ModelState:
    """Return the state with its residual model's coefficients refined (module docstring).

    The prior's weight is chosen among ``PRIOR_WEIGHTS`` (and no refinement) by two-fold
    cross-validation on the segments (interleaved time blocks of each drive): the weight whose
    refinement on one half gives the other half the lowest end-pose loss, summed over both.
    A state without a residual model, without coefficients in use or without their covariance
    is returned as it is, as is one where no weight beats the velocity fit.
    """
    name = _regression(state)
    if name is None or not state.residual_covariance or not state.terms(name):
        return state
    seg = predictor.segments
    rows = np.arange(len(seg)) if keep is None else np.asarray(keep)
    if rows.size < 2 * MIN_FOLD_SEGMENTS or len(PRIOR_WEIGHTS) == 0:
        return state
    labels = block_folds(seg.drive[rows], seg.t_a_ns[rows], 2)
    scores = {}
    for weight in (None,) + tuple(PRIOR_WEIGHTS):
        total = 0.0
        for fold in (0, 1):
            train, test = rows[labels != fold], rows[labels == fold]
            if min(train.size, test.size) < MIN_FOLD_SEGMENTS:
                return state
            fitted = (state if weight is None else
                      refine_at(predictor, base_name, geometry, state, options, train, weight))
            total += float(held_out_loss(predictor, fitted.bind(base_name, geometry), options,
                                         test).sum())
        scores[weight] = total
    best = min(scores, key=lambda w: scores[w])
    if best is None:
        return state
    return refine_at(predictor, base_name, geometry, state, options, keep, best)


def refine_at(predictor: SegmentPredictor, base_name: str, geometry: Geometry, state: ModelState,
              options: DiagnosisOptions, keep: np.ndarray | None, prior_weight: float,
              iterations: int | None = None) -> ModelState:
    """Refine at one weight of the prior precision (steps 1-4 of the module docstring)."""
    iterations = REFINE_ITERATIONS if iterations is None else iterations
    name = _regression(state)
    if name is None or not state.residual_covariance:
        return state
    terms = state.terms(name)
    if not terms:
        return state
    ext = get_extension(name)
    names = residual.coefficient_names()
    where = [names.index(t) for t in terms]   # position in the covariance and the parameters
    index = state.extensions.index(name)
    free = [(index, ext.param_names.index(t)) for t in terms]
    full = np.asarray(state.residual_covariance, dtype=float).reshape(len(names), len(names))
    prior = _prior_precision(full[np.ix_(where, where)]) * prior_weight
    mean = np.array([state.ext_values[name][t] for t in terms])
    weight = options.whitening

    def with_coefs(coefs: np.ndarray) -> ModelState:
        values = {k: dict(v) for k, v in state.ext_values.items()}
        values[name].update(zip(terms, (float(c) for c in coefs)))
        return ModelState(state.extensions, state.base_values, values, state.sparse_terms,
                          state.found, state.residual_covariance)

    def residuals(coefs: np.ndarray) -> np.ndarray:
        source = with_coefs(coefs).bind(base_name, geometry)
        return whitened_residuals(predictor.errors(source, keep), weight)

    def jacobian(coefs: np.ndarray) -> np.ndarray:
        source = with_coefs(coefs).bind(base_name, geometry)
        jac = predictor.errors_jacobian(source, free, None, keep)
        white = np.asarray(weight, dtype=float)
        jac = (np.einsum('nij,njp->nip', white, jac) if white.ndim == 3
               else jac * white[None, :, None])
        return np.nan_to_num(jac).reshape(-1, len(free))

    coefs = mean.copy()
    r = residuals(coefs)
    if r.size <= len(free) or not np.all(np.abs(r) < 1e5):
        return state
    s2 = max(float(r @ r) / (r.size - len(free)), 1e-300)

    def objective(c: np.ndarray, res: np.ndarray) -> float:
        d = c - mean
        return float(res @ res) / s2 + float(d @ prior @ d)

    cost = objective(coefs, r)
    damping = 0.0
    jac = None
    for _ in range(iterations):
        jac = jacobian(coefs)
        hess = jac.T @ jac / s2 + prior
        grad = jac.T @ r / s2 + prior @ (coefs - mean)
        improved = False
        for _ in range(6):
            step = -np.linalg.solve(hess + damping * np.diag(np.diag(hess)), grad)
            trial = np.clip(coefs + step, -COEF_LIMIT, COEF_LIMIT)
            r_trial = residuals(trial)
            cost_trial = objective(trial, r_trial)
            if cost_trial < cost:
                coefs, r, cost, improved = trial, r_trial, cost_trial, True
                damping = damping / 10.0 if damping > 1e-6 else 0.0
                break
            damping = max(10.0 * damping, 1e-3)
        if not improved:
            break
    jac = jacobian(coefs)
    post = np.linalg.inv(jac.T @ jac / s2 + prior)
    seg = predictor.segments
    drive = seg.drive if keep is None else seg.drive[keep]
    start = seg.t_a_ns if keep is None else seg.t_a_ns[keep]
    order = np.lexsort((start, drive))
    white = whiten(predictor.errors(with_coefs(coefs).bind(base_name, geometry), keep),
                   weight)
    rho = max(autocorrelation(np.nan_to_num(white[order, c]), drive[order]) for c in range(3))
    post *= (1.0 + rho) / (1.0 - rho)
    post = 0.5 * (post + post.T)
    cov = full.copy()
    cov[np.ix_(where, where)] = post
    refined = with_coefs(coefs)
    return ModelState(refined.extensions, refined.base_values, refined.ext_values,
                      refined.sparse_terms, refined.found, tuple(cov.ravel().tolist()))
