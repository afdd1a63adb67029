"""Fit the data-driven residual model: Bayesian linear regression on the per-pose residuals.

The residual model (:mod:`skidkin_ros.core.kinematics.residual`) corrects the body twist by
C phi(z), phi a fixed library of smooth terms of the wheel-speed state z = (v, w, dv, dw), in
levels. It is fitted as Norlab's DRIVE fits body-frame slip, as a recipe:

1. **Inputs.** At every fresh ground-truth pose, the twist the residual model would see (the
   current model's twist before it, of the held wheel speeds) and the base twist's rate; the
   target is the per-pose body-velocity residual of the current model
   (:func:`~.residuals.pose_residuals`), component by component (v_x, v_y, omega); the terms it
   is regressed on are the library's as that windowed target sees them (integrated over the
   wheel samples, then differentiated by the same window: :mod:`.window_features`).
2. **Range.** Each input's fitted range is its 0.5 .. 99.5 percentile over the poses used; the
   terms are computed on the inputs clamped to it and scaled to [-1, 1] (outside the range the
   correction holds its edge value: it cannot run away where it has not seen data).
3. **Regression.** For each component and each library level, Bayesian linear regression with a
   Gaussian prior on the (standardised) coefficients, its precision alpha and the noise
   precision beta set by maximising the evidence (MacKay's fixed point).
4. **Complexity on held-out likelihood.** The poses are split into time blocks (``BLOCK_FOLDS``
   interleaved groups per drive); for each component, the level (0: no correction) whose
   predictive density N(y; phi^T m, 1/beta + phi^T S phi) gives the held-out poses the highest
   log-likelihood is kept; a simpler level within ``LEVEL_TIE_NATS`` per pose of it is kept
   instead (a tie is no gain).
5. **Uncertainty.** The posterior covariance S of the kept coefficients is inflated by n / n_eff,
   n_eff = n (1 - rho) / (1 + rho) with rho the lag-one autocorrelation of the fitted residual
   (neighbouring poses share the ground truth's smoothing, so they are not independent
   measurements); it goes into the parameters file and the published covariance.

Whether the correction is added at all is then the selection's decision, on the held-out end-pose
errors of whole segments (:mod:`.select_extensions`), like any extension.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Sequence

import numpy as np

from skidkin_ros.core.calibration.diagnosis.options import DiagnosisOptions
from skidkin_ros.core.calibration.diagnosis.residuals import (base_rates, pose_residuals,
                                                              PoseSamples)
from skidkin_ros.core.calibration.diagnosis.window_features import window_terms
from skidkin_ros.core.calibration.engine import TwistSource
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.kinematics import residual
from skidkin_ros.core.kinematics.augmented import BoundAugmented
from skidkin_ros.core.kinematics.extensions import get_extension

__all__ = ['autocorrelation', 'BLOCK_FOLDS', 'COEF_LIMIT', 'Regression', 'ResidualFit', 'blr',
           'block_folds', 'fit_residual_model', 'model_inputs', 'RANGE_PERCENTILES']

BLOCK_FOLDS = 4
RANGE_PERCENTILES = (0.5, 99.5)
_EVIDENCE_ITERATIONS = 50
COEF_LIMIT = 9.9  # inside the coefficients' bounds (+-10)
# A level must beat a simpler one by this much held-out log-likelihood per pose (nats).
LEVEL_TIE_NATS = 0.002
# Fit on the terms as the target sees them (:mod:`.window_features`), the target over a half
# window of TARGET_WINDOW_S (None: the options' smoothing_s).
WINDOW_TERMS = True
TARGET_WINDOW_S: float | None = None


@dataclass(frozen=True)
class Regression:
    """One Bayesian linear regression: posterior mean and covariance, precisions, evidence."""

    mean: np.ndarray
    cov: np.ndarray
    alpha: float
    beta: float

    def predict(self, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the predictive mean and variance at the rows of ``phi``."""
        mean = phi @ self.mean
        # phi S phi^T's diagonal through one product (a 3-operand einsum is 15x slower)
        var = 1.0 / self.beta + np.einsum('ij,ij->i', phi @ self.cov, phi)
        return mean, var

    def log_likelihood(self, phi: np.ndarray, y: np.ndarray) -> float:
        mean, var = self.predict(phi)
        return float(-0.5 * np.sum(np.log(2.0 * math.pi * var) + (y - mean) ** 2 / var))


def blr(phi: np.ndarray, y: np.ndarray) -> Regression:
    """Bayesian linear regression with evidence-maximised prior and noise precisions.

    The prior is on the coefficients of the columns scaled to unit RMS (one alpha means the same
    for every term); the result is for the columns as given.
    """
    n, p = phi.shape
    rms = np.sqrt(np.mean(phi ** 2, axis=0)) if n else np.ones(p)
    rms = np.where(rms > 1e-12, rms, 1.0)
    z = phi / rms
    gram = z.T @ z
    zy = z.T @ y
    yy = float(y @ y)
    # In the eigenbasis of the Gram matrix every iteration is O(p^2): no n-sized product.
    eig, vec = np.linalg.eigh(gram)
    eig = np.clip(eig, 0.0, None)
    proj = vec.T @ zy
    alpha, beta = 1.0, 1.0 / max(float(np.var(y)), 1e-12)
    for _ in range(_EVIDENCE_ITERATIONS):
        mean_e = beta * proj / (alpha + beta * eig)   # posterior mean in the eigenbasis
        gamma = float(np.sum(beta * eig / (alpha + beta * eig)))
        new_alpha = gamma / max(float(mean_e @ mean_e), 1e-300)
        sse = max(yy - 2.0 * float(mean_e @ proj) + float(mean_e @ (eig * mean_e)), 1e-300)
        new_beta = max(n - gamma, 1e-9) / sse
        new_alpha = min(max(new_alpha, 1e-9), 1e12)
        done = (abs(new_alpha - alpha) <= 1e-6 * alpha and abs(new_beta - beta) <= 1e-6 * beta)
        alpha, beta = new_alpha, new_beta
        if done:
            break
    inverse = 1.0 / (alpha + beta * eig)
    cov = (vec * inverse) @ vec.T
    mean = beta * cov @ zy
    return Regression(mean / rms, cov / np.outer(rms, rms), alpha, beta)


def block_folds(drive: np.ndarray, t_ns: np.ndarray, folds: int = BLOCK_FOLDS) -> np.ndarray:
    """Label each pose with a fold: 3 x ``folds`` contiguous time blocks per drive, interleaved."""
    labels = np.zeros(drive.size, dtype=int)
    blocks = 3 * folds
    for d in np.unique(drive):
        rows = np.nonzero(drive == d)[0]
        order = rows[np.argsort(t_ns[rows], kind='stable')]
        labels[order] = ((np.arange(order.size) * blocks) // max(order.size, 1)) % folds
    return labels


def model_inputs(drives: Sequence[Drive], samples: PoseSamples, source: TwistSource,
                 options: DiagnosisOptions) -> tuple[np.ndarray, np.ndarray]:
    """Return the residual model's inputs at the poses: its incoming twist and the base rate.

    The incoming twist is the source's twist-stage output of the held wheel speeds (the base
    twist for a plain model), the rate the base twist's as the integrator has it.
    """
    wl, wr = samples.signals['omega_l'], samples.signals['omega_r']
    base = source.base if isinstance(source, BoundAugmented) else source
    rate = np.zeros((wl.size, 3))
    for index in np.unique(samples.drive):
        rows = np.nonzero(samples.drive == index)[0]
        wheels = drives[index].wheels
        held = np.clip(np.searchsorted(wheels.t_ns, samples.t_ns[rows], side='right') - 1, 0,
                       len(wheels) - 1)
        rate[rows] = base_rates(wheels, base, options.max_dt_s)[held]
    twist = np.asarray(base.twist(wl, wr), dtype=float)
    if isinstance(source, BoundAugmented):
        t_s = samples.signals['time_in_drive']
        for name, k in zip(source.extensions, source.values):
            ext = get_extension(name)
            if ext.regression:
                break
            twist = ext.apply(k, twist, wl, wr, t_s, rate)
    return twist, rate


@dataclass(frozen=True)
class ResidualFit:
    """The fitted residual model: extension values, terms in use, covariance, what was chosen.

    ``levels``: the level kept for each output; ``scores``: {output: {level: held-out
    log-likelihood}}; ``inflation``: the n / n_eff factor applied to the covariance.
    """

    values: dict[str, float]
    terms: tuple[str, ...]
    covariance: tuple[float, ...]
    levels: tuple[int, int, int]
    scores: dict[str, dict[int, float]]
    inflation: float


def _ranges(twist: np.ndarray, rate: np.ndarray) -> list[float]:
    raw = residual.input_values(twist, rate)
    out = []
    for x in raw:
        finite = x[np.isfinite(x)]
        if finite.size == 0:
            out += [0.0, 0.0]
            continue
        lo, hi = np.percentile(finite, RANGE_PERCENTILES)
        out += [float(min(lo, 0.0)), float(max(hi, 0.0))]
    return out


def _null_log_likelihood(train: np.ndarray, test: np.ndarray) -> float:
    var = max(float(np.mean(train ** 2)), 1e-12)
    return float(-0.5 * np.sum(np.log(2.0 * math.pi * var) + test ** 2 / var))


def autocorrelation(errors: np.ndarray, drive: np.ndarray) -> float:
    """Return the lag-one autocorrelation of ``errors`` within each drive, in [0, 0.99]."""
    num = den = 0.0
    for d in np.unique(drive):
        e = errors[drive == d]
        if e.size < 3:
            continue
        e = e - e.mean()
        num += float(e[1:] @ e[:-1])
        den += float(e @ e)
    return float(np.clip(num / den, 0.0, 0.99)) if den > 0 else 0.0


def fit_residual_model(drives: Sequence[Drive], samples: PoseSamples, source: TwistSource,
                       options: DiagnosisOptions, use: np.ndarray | None = None
                       ) -> ResidualFit:
    """Fit the residual model on the poses ``use`` (bool mask, None: all) (module docstring)."""
    twist, rate = model_inputs(drives, samples, source, options)
    ok = np.all(np.isfinite(twist), axis=1) & np.all(np.isfinite(rate), axis=1)
    if use is not None:
        ok &= use
    if WINDOW_TERMS:   # the terms as the target sees them, over the target's window
        ranges = _ranges(twist[ok & samples.valid], rate[ok & samples.valid])
        target, valid, moving, turning = window_terms(
            drives, samples, source, options, ranges, TARGET_WINDOW_S or options.smoothing_s)
        ok &= np.all(np.isfinite(moving), axis=1) & np.all(np.isfinite(turning), axis=1)
    else:
        target, valid = pose_residuals(drives, samples, source, options)
    ok &= valid & np.all(np.isfinite(target), axis=1)
    rows = np.nonzero(ok)[0]
    if WINDOW_TERMS:
        terms_of = (moving[rows], moving[rows], turning[rows])
    else:
        ranges = _ranges(twist[rows], rate[rows])
        phi = residual.features(ranges, twist[rows], rate[rows])
        terms_of = (phi, phi, phi)
    folds = block_folds(samples.drive[rows], samples.t_ns[rows])
    names = residual.term_names()
    count = len(names)
    coef = np.zeros((len(residual.OUTPUTS), count))
    cov = np.zeros((len(residual.OUTPUTS) * count,) * 2)
    levels = []
    scores: dict[str, dict[int, float]] = {}
    errors = []
    splits: dict[int, list] = {}   # each fold's rows, taken once per term array for every level
    for c, (out, _) in enumerate(residual.OUTPUTS):
        y = target[rows, c]
        phi_all = terms_of[c]
        split = splits.get(id(phi_all))
        if split is None:
            split = splits[id(phi_all)] = [
                (folds == fold, phi_all[folds != fold], phi_all[folds == fold])
                for fold in range(BLOCK_FOLDS)]
        score = {0: 0.0}
        for level in residual.LEVELS:
            score[level] = 0.0
        for test, phi_train, phi_test in split:
            if not test.any() or test.all():
                continue
            score[0] += _null_log_likelihood(y[~test], y[test])
            for level in residual.LEVELS:
                cols = [j for j, (_, lvl, _, _) in enumerate(residual.TERMS) if lvl <= level]
                fit = blr(phi_train[:, cols], y[~test])
                score[level] += fit.log_likelihood(phi_test[:, cols], y[test])
        top = max(score.values())
        # the simplest level within LEVEL_TIE_NATS per pose of the best (a tie is no gain)
        best = min(level for level in score if score[level] >= top - LEVEL_TIE_NATS * y.size)
        levels.append(best)
        scores[out] = score
        if best == 0 or rows.size == 0:
            errors.append(y)
            continue
        cols = [j for j, (_, lvl, _, _) in enumerate(residual.TERMS) if lvl <= best]
        fit = blr(phi_all[:, cols], y)
        coef[c, cols] = np.clip(fit.mean, -COEF_LIMIT, COEF_LIMIT)
        index = [c * count + j for j in cols]
        cov[np.ix_(index, index)] = fit.cov
        errors.append(y - phi_all[:, cols] @ fit.mean)
    rho = max((autocorrelation(e, samples.drive[rows]) for e in errors), default=0.0)
    inflation = (1.0 + rho) / (1.0 - rho)
    cov *= inflation
    cov = 0.5 * (cov + cov.T)
    values = {f'{out}_{term}': float(coef[c, j]) for c, (out, _) in enumerate(residual.OUTPUTS)
              for j, term in enumerate(names)}
    values.update(zip(residual.range_names(), ranges))
    values['level'] = float(max(levels))
    terms = tuple(name for name, value in values.items()
                  if name.startswith(('vx_', 'vy_', 'wz_')) and value != 0.0)
    return ResidualFit(values, terms, tuple(cov.ravel().tolist()), tuple(levels), scores,
                       inflation)
