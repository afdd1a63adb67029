"""Choose the best model on a criterion that counts heading: the held-out likelihood.

The paper's metrics (eps_t, eps_theta) score position and heading apart, and a rule that adds
their ratios trades one for the other at an arbitrary rate. The negative log-likelihood of the
held-out end-pose errors under each model's own calibrated noise counts x, y and heading on the
scale of their predicted covariances, so a model that drifts in heading pays for it.

Held-out NLL per segment (two-fold, by cluster): the evaluation segments are split into two
folds by cluster (a drive, or the value of the hold-out key, e.g. the DRIVE ``calib_step``:
segments of one command are not independent); the noise model is fitted on one fold
(:func:`skidkin_ros.core.calibration.weighting.noise_covariances`) and each segment of the other
fold scores 0.5 (log det Sigma_i + e_i^T Sigma_i^-1 e_i + 3 log 2 pi), and back.

Rule (:func:`choose_by_likelihood`): among the valid fits, the model with the lowest mean NLL
is the reference; for every model, the mean of its paired per-segment differences to the
reference and the standard error of that mean, clustered by the same clusters. Every model
within 2 standard errors of the reference is a tie, and among the ties the one with the fewest
parameters wins (then the lowest NLL).

The paper's score (:func:`paper_scores`), for the fallback rule and the sample-interval choice:
median eps_t / (best median eps_t) + median eps_theta / (best median eps_theta); the candidates
within ``TIE_TOLERANCE`` (2 %) of the lowest score are ties (:func:`paper_ties`), each caller
breaking them its own way.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Mapping, Sequence

import numpy as np

from skidkin_ros.core.calibration.fitting import segment_errors
from skidkin_ros.core.calibration.noise_fit import mahalanobis
from skidkin_ros.core.calibration.segments import SegmentSet
from skidkin_ros.core.calibration.weighting import noise_covariances
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.errors import DataError, FitError

__all__ = ['TIE_STANDARD_ERRORS', 'TIE_TOLERANCE', 'Likelihood', 'segment_clusters',
           'heldout_nll', 'clustered_standard_error', 'choose_by_likelihood', 'paper_scores',
           'paper_ties']

TIE_STANDARD_ERRORS = 2.0
TIE_TOLERANCE = 0.02
LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class Likelihood:
    """One model's held-out NLL and its paired difference to the lowest."""

    mean_nll: float
    delta: float = math.nan            # mean paired difference to the lowest model
    standard_error: float = math.nan   # of delta, clustered
    parameters: int = 0


def segment_clusters(segments: SegmentSet, drives: Sequence[Drive],
                     key: str | None = None) -> np.ndarray:
    """Return a cluster label per segment: the drive's ``key`` value, else the drive."""
    labels = []
    for index in segments.drive:
        meta = getattr(drives[int(index)], 'meta', None) or {}
        value = meta.get(key) if key else None
        labels.append(f'{key}={value}' if value is not None else f'drive {int(index)}')
    _, codes = np.unique(np.array(labels, dtype=object).astype(str), return_inverse=True)
    return codes


def heldout_nll(name: str, values: Mapping[str, float], geometry: Geometry,
                segments: SegmentSet, clusters: np.ndarray) -> np.ndarray:
    """Return each segment's two-fold held-out NLL (module docstring); raises DataError."""
    model = get_model(name)
    errors = segment_errors(model, model.vector(dict(values), geometry), geometry, segments)
    order = np.unique(clusters)
    if order.size < 2:
        raise DataError('the held-out likelihood needs evaluation data from at least 2 drives '
                        'or hold-out groups')
    fold = np.isin(clusters, order[1::2])
    out = np.full(len(segments), np.inf)
    finite = np.all(np.isfinite(errors), axis=1)
    for part in (False, True):
        fit_idx = np.nonzero((fold == part) & finite)[0]
        check_idx = np.nonzero((fold != part) & finite)[0]
        if check_idx.size == 0:
            continue
        if fit_idx.size == 0:
            raise DataError('the held-out likelihood needs finite errors in both halves of the '
                            'evaluation data')
        cov = noise_covariances(name, dict(values), geometry, segments.subset(fit_idx),
                                errors[fit_idx], segments.subset(check_idx))
        err = errors[check_idx]
        sign, logdet = np.linalg.slogdet(cov)
        maha = mahalanobis(cov, err)
        out[check_idx] = np.where(sign > 0, 0.5 * (logdet + maha + 3 * LOG_2PI), np.inf)
    return out


def clustered_standard_error(values: np.ndarray, clusters: np.ndarray) -> float:
    """Return the standard error of mean(values), cluster-robust (sums of deviations)."""
    n = values.size
    if n < 2:
        return math.inf
    dev = values - values.mean()
    sums = np.bincount(np.unique(clusters, return_inverse=True)[1], weights=dev)
    groups = sums.size
    if groups < 2:
        return math.inf
    return float(math.sqrt(groups / (groups - 1) * float((sums ** 2).sum())) / n)


def choose_by_likelihood(nll: Mapping[str, np.ndarray], clusters: np.ndarray,
                         parameters: Mapping[str, int]) -> tuple[str, dict[str, Likelihood]]:
    """Apply the rule of the module docstring to valid models' per-segment NLLs."""
    usable = {m: v for m, v in nll.items() if np.all(np.isfinite(v))}
    if not usable:
        raise FitError('no valid model has a finite held-out likelihood; see the warnings')
    lowest = min(usable, key=lambda m: float(usable[m].mean()))
    table = {}
    for m, values in nll.items():
        if m not in usable:
            table[m] = Likelihood(math.inf, math.inf, math.nan, parameters[m])
            continue
        diff = values - usable[lowest]
        table[m] = Likelihood(float(values.mean()), float(diff.mean()),
                              0.0 if m == lowest else clustered_standard_error(diff, clusters),
                              parameters[m])
    tied = [m for m in usable
            if table[m].delta <= TIE_STANDARD_ERRORS * table[m].standard_error or m == lowest]
    best = min(tied, key=lambda m: (table[m].parameters, table[m].mean_nll))
    return best, table


def paper_scores(medians: Mapping[str, tuple[float, float]]) -> dict[str, float]:
    """Return each candidate's paper score (module docstring) from its held-out medians.

    ``medians``: {candidate: (median eps_t m/m, median eps_theta deg/m)}, the candidates to
    compare (the caller leaves out those it does not score); a best median below 1e-12 counts
    as 1e-12.
    """
    best_t = max(min(v[0] for v in medians.values()), 1e-12)
    best_th = max(min(v[1] for v in medians.values()), 1e-12)
    return {k: v[0] / best_t + v[1] / best_th for k, v in medians.items()}


def paper_ties(scores: Mapping[str, float], order: Sequence[str]) -> list[str]:
    """Return the candidates of ``order`` scored within TIE_TOLERANCE of the lowest score."""
    lowest = min(scores.values())
    return [k for k in order if k in scores and scores[k] <= lowest * (1.0 + TIE_TOLERANCE)]
