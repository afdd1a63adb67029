"""The residual model's own uncertainty, carried into the published pose covariance.

The residual model's coefficients C are known up to their posterior covariance Sigma_C (Bayesian
linear regression, inflated for the residuals' autocorrelation; written as
``augmented.residual_model.covariance``). Like the base model's parameter covariance
(:mod:`skidkin_ros.core.odometry.uncertainty`), an error in C is the same for the whole drive, so
the pose error it causes grows with the distance: the propagator carries the sensitivity
S = d pose / d C by the same step, S' = F S + G dt d(twist)/dC, and publishes S Sigma_C S^T on top.

The correction is linear in C, so d(twist)/dC is the library's terms at the state that gave the
step's twist (:func:`skidkin_ros.core.kinematics.extensions.residual_jacobian`; the bound on the
change and a lag's smoothing of the sensitivity are left out, a first-order view). Only the
coefficients with a non-zero variance are carried: a step costs a few multiplications per term in
use, at most 60.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from skidkin_ros.core.kinematics.extensions import get_extension, residual_jacobian

__all__ = ['ResidualUncertainty', 'RESIDUAL_EXTENSION']

RESIDUAL_EXTENSION = 'residual_model'


@dataclass(frozen=True)
class ResidualUncertainty:
    """Sigma_C of the coefficients in use and the extension's values (module docstring)."""

    covariance: np.ndarray          # (p, p): the coefficients in use
    index: tuple[int, ...]          # their positions among the extension's coefficients
    values: tuple[float, ...]       # every parameter of the extension (coefficients, ranges)

    @classmethod
    def of(cls, values: Sequence[float], covariance: np.ndarray
           ) -> 'ResidualUncertainty | None':
        """Return the uncertainty to carry; None when no coefficient has a variance."""
        covariance = np.asarray(covariance, dtype=float)
        index = tuple(int(i) for i in np.nonzero(np.diag(covariance) > 0.0)[0])
        if not index:
            return None
        sub = covariance[np.ix_(index, index)]
        return cls(sub, index, tuple(float(v) for v in values))

    @property
    def size(self) -> int:
        return len(self.index)

    def twist_jacobian(self, vx: float, vy: float, w: float,
                       wheels: tuple[float, float] | None = None) -> None:
        """Not from the twist alone: the caller gives :meth:`jacobian` of the step's state."""
        return None

    def jacobian(self, state) -> list[tuple[float, float, float]] | None:
        """Return d(twist)/dC of the coefficients in use at an augmented state (None: no state)."""
        if state is None:
            return None
        return residual_jacobian(self.values, state.b, state.r, self.index)

    def pose_covariance(self, sens: Sequence[Sequence[float]]) -> tuple[float, ...]:
        """Upper triangle of S Sigma_C S^T for S given as p columns (d x, d y, d yaw)/dC_j."""
        s = np.asarray(sens, dtype=float).T  # (3, p)
        c = s @ self.covariance @ s.T
        return (float(c[0, 0]), float(c[0, 1]), float(c[0, 2]), float(c[1, 1]), float(c[1, 2]),
                float(c[2, 2]))


def coefficient_count() -> int:
    """Return how many coefficients the residual model has (the covariance's side)."""
    ext = get_extension(RESIDUAL_EXTENSION)
    return sum(1 for name in ext.param_names if name.startswith(('vx_', 'vy_', 'wz_')))
