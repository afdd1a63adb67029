"""The calibration's own uncertainty: how an error in the fitted parameters moves the pose.

After calibration the parameters k are known up to their covariance Sigma_k (the fit's, written
per model to the parameters file as ``models.<m>.parameter_covariance``). An error dk is the same
for the whole drive, so the pose error it causes grows in proportion to the distance, not with
its square root like the per-metre noise: over a whole drive it dominates, and a covariance
without it is over-confident (NEES 5.2 over 300 s simulated drives). With S = d pose / d k, the
sensitivity of the integrated pose to the parameters, the pose covariance gains S Sigma_k S^T.

S is propagated alongside the pose covariance by the same step (first order):

    S' = F S + G dt d(twist)/dk

F and G are the step's Jacobians (:func:`skidkin_ros.core.odometry.propagation.step_jacobians`),
and d(twist)/dk is taken at the twist of the step. For a model linear in the wheel speeds
(twist = R(k) w) it is a function of the twist alone: d(twist)/dk_j = dR/dk_j R^+ twist, with
R^+ the pseudo-inverse (the twist lies in the range of R, so R^+ twist recovers w exactly). The
matrices M_j = dR/dk_j R^+ are computed once per model (:class:`ParameterUncertainty`), so a
step costs a few dozen multiplications and does not depend on which wheel sample the integrator
holds over the step. A model not linear in the wheel speeds (ROC) needs the speeds integrated over
the step: d(twist)/dk is then a central difference of the model's twist at them, two twist
evaluations per parameter and step (the integrator reports the speeds of every step, an
augmented model's included: online learning of an augmented model carries its sensitivity by
:class:`~skidkin_ros.core.online.augmented.LayoutUncertainty`).

Per wheel sample, for a linear model, the step of S is one loop over its p columns on floats
(:class:`~skidkin_ros.core.odometry.propagation.PoseCovariancePropagator`). The file's fixed
Sigma_k is read as S Sigma_k S^T, as it always was; a learner's Sigma_k, which changes while
the robot drives, is carried in its eigenbasis, T = S V with Sigma_k = V diag(lambda) V^T (the
matrices M_j rotated once per parameter set, :attr:`ParameterUncertainty.eigen`), so the read is
sum_l lambda_l t_l t_l^T, p outer products of 3-vectors, and a new Sigma_k only rotates T (V
is orthogonal: the numbers stay those of S Sigma_k S^T to rounding).
"""

from __future__ import annotations

from dataclasses import dataclass
import functools
from typing import Any, Sequence

import numpy as np

from skidkin_ros.errors import ParameterError

__all__ = ['ParameterUncertainty', 'check_parameter_covariance']


def check_parameter_covariance(name: str, values: Sequence[float], size: int) -> np.ndarray:
    """Return a flat row-major covariance as a (size, size) matrix, or raise ParameterError."""
    matrix = np.asarray(values, dtype=float)
    if matrix.size != size * size or not np.all(np.isfinite(matrix)):
        raise ParameterError(f'parameter {name!r} must hold {size * size} finite numbers (a '
                             f'{size} x {size} covariance, row-major), got {list(values)[:8]}')
    matrix = matrix.reshape(size, size)
    if not np.allclose(matrix, matrix.T, rtol=1e-6, atol=1e-15):
        raise ParameterError(f'parameter {name!r} is not symmetric; write the covariance the '
                             'calibrator wrote or zeros (no parameter uncertainty)')
    matrix = 0.5 * (matrix + matrix.T)
    if size and np.linalg.eigvalsh(matrix).min() < -1e-9 * max(np.abs(matrix).max(), 1e-300):
        raise ParameterError(f'parameter {name!r} is not positive semi-definite; write the '
                             'covariance the calibrator wrote or zeros (no parameter uncertainty)')
    return matrix


def _central_differences(function, k: np.ndarray, rel_step: float) -> list[np.ndarray]:
    """Return d function / dk_j for every j, central differences of step rel_step max(|k_j|, 1)."""
    out = []
    for j in range(k.size):
        step = rel_step * max(abs(float(k[j])), 1.0)
        plus, minus = k.copy(), k.copy()
        plus[j] += step
        minus[j] -= step
        out.append((np.asarray(function(plus), dtype=float)
                    - np.asarray(function(minus), dtype=float)) / (2.0 * step))
    return out


@dataclass(frozen=True)
class ParameterUncertainty:
    """Sigma_k of one bound linear model and the twist sensitivity matrices M_j (module doc)."""

    covariance: np.ndarray              # (p, p)
    sensitivity: tuple[tuple[float, ...], ...]  # p rows of 9 floats: M_j row-major
    # A model not linear in the wheel speeds: (model, k, geometry, rel_step); sensitivity is ().
    nonlinear: tuple[Any, tuple[float, ...], Any, float] | None = None

    @classmethod
    def of_model(cls, model, k: np.ndarray, geometry, covariance: np.ndarray,
                 rel_step: float = 1e-6) -> 'ParameterUncertainty | None':
        """Return the uncertainty of ``model`` at ``k``; None when it cannot be propagated.

        None: no parameter or an all-zero covariance.
        """
        k = np.asarray(k, dtype=float)
        covariance = np.asarray(covariance, dtype=float)
        if k.size == 0 or not np.any(covariance):
            return None
        rows = model.rows(k, geometry)
        if rows is None:
            return cls(covariance, (), (model, tuple(float(v) for v in k), geometry, rel_step))
        pinv = np.linalg.pinv(np.asarray(rows, dtype=float))
        d_rows = _central_differences(lambda kk: model.rows(kk, geometry), k, rel_step)
        return cls(covariance, tuple(tuple((d @ pinv).ravel().tolist()) for d in d_rows))

    @property
    def size(self) -> int:
        return len(self.nonlinear[1]) if self.nonlinear is not None else len(self.sensitivity)

    def twist_jacobian(self, vx: float, vy: float, w: float,
                       wheels: tuple[float, float] | None = None
                       ) -> list[tuple[float, float, float]] | None:
        """Return d(twist)/dk_j for every j as (d vx, d vy, d w) triples.

        A model not linear in the wheel speeds needs ``wheels`` (the speeds integrated over the
        step); without them it returns None (nothing can be carried).
        """
        if self.nonlinear is not None:
            return None if wheels is None else self._wheel_jacobian(*wheels)
        out = []
        for m0, m1, m2, m3, m4, m5, m6, m7, m8 in self.sensitivity:
            out.append((m0 * vx + m1 * vy + m2 * w, m3 * vx + m4 * vy + m5 * w,
                        m6 * vx + m7 * vy + m8 * w))
        return out

    def _wheel_jacobian(self, omega_l: float, omega_r: float
                        ) -> list[tuple[float, float, float]]:
        model, k, geometry, rel_step = self.nonlinear
        d_twist = _central_differences(
            lambda kk: model.twist(kk, geometry, omega_l, omega_r), np.asarray(k, dtype=float),
            rel_step)
        return [tuple(float(v) for v in d.reshape(3)) for d in d_twist]

    @functools.cached_property
    def eigen(self) -> tuple[tuple[float, ...], np.ndarray, tuple[tuple[float, ...], ...]]:
        """Return Sigma_k's eigen-decomposition and the sensitivity in its basis (linear model).

        (weights, basis, rotated): Sigma_k = V diag(weights) V^T with V = ``basis`` (p, p,
        orthogonal), and ``rotated`` the matrices M'_l = sum_j V_jl M_j (9 floats each, as
        :attr:`sensitivity`). A sensitivity T = S V carried with M' instead of M gives
        S Sigma_k S^T = sum_l weights_l t_l t_l^T: p outer products of 3-vectors instead of two
        matrix products when the covariance is read. V is orthogonal, so moving T from one
        parameter covariance's basis to the next (T V_old^T V_new) only rounds.
        """
        weights, basis = np.linalg.eigh(0.5 * (self.covariance + self.covariance.T))
        rows = np.asarray(self.sensitivity, dtype=float).reshape(-1, 9)
        rotated = basis.T @ rows
        return (tuple(weights.tolist()), basis,
                tuple(tuple(row) for row in rotated.tolist()))

    def pose_covariance(self, sens: Sequence[Sequence[float]]) -> tuple[float, ...]:
        """Upper triangle of S Sigma_k S^T for S given as p columns (d x, d y, d yaw)/dk_j."""
        s = np.asarray(sens, dtype=float).T  # (3, p)
        (c00, c01, c02), (_, c11, c12), (_, _, c22) = (s @ self.covariance @ s.T).tolist()
        return c00, c01, c02, c11, c12, c22
