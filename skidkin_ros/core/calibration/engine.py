"""One least-squares engine for every fit: the five models and the diagnosis's augmented ones.

A fit, as a recipe:

1. **Layout.** A :class:`ParameterLayout` says which parameters the optimizer moves: some or all
   of the base model's, then some of each extension's; the others keep their values. Bounds come
   from each parameter's ParamSpec (open bounds pulled in by a small margin), so a name or a range
   is written once (:mod:`skidkin_ros.core.kinematics.specs`).
2. **Errors.** The caller says how a twist source is scored: the end-pose errors (N, 3) of its
   segments in each segment's start frame (a plain rollout for the five models, the
   :class:`~skidkin_ros.core.calibration.predictor.SegmentPredictor` for stateful sources).
3. **Whitening.** Errors are multiplied by W (W^T W = Sigma^-1): metres and radians on one
   unitless scale, and the loss l = sum_i e_i^T Sigma_i^-1 e_i. W is either one diagonal for
   every segment (a vector (3,), Sigma = diag(sigma_diag)) or one matrix per segment (N, 3, 3),
   as the iterated fit of :mod:`skidkin_ros.core.calibration.weighting` gives it.
4. **Non-finite predictions.** A parameter vector far from the data can make a prediction NaN or
   infinite (a spin's yaw rate divided by a vanishing ICR distance). Such an error becomes
   +-``NONFINITE_PENALTY`` whitened units: a wall the optimizer backs away from instead of a
   failure; a held-out loss counts such a segment as ``NONFINITE_PENALTY`` (see
   :func:`segment_losses`).
5. **Solve.** scipy's bounded ``least_squares`` (trust-region reflective, ``x_scale='jac'``, an
   optional robust loss), at most ``max_nfev`` (p + 1) evaluations for p free parameters. A
   layout without a free parameter is evaluated, not solved.

Outlier trimming (C15) lives here too, because both fits drop the same outliers the same way:
:func:`trim_mask`.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Callable, Mapping, Sequence, Union

import numpy as np
from scipy import optimize, stats

from skidkin_ros.core.kinematics.augmented import BoundAugmented
from skidkin_ros.core.kinematics.extensions import get_extension
from skidkin_ros.core.kinematics.models import BoundModel, get_model
from skidkin_ros.core.kinematics.specs import Geometry, ParamSpec
from skidkin_ros.errors import ParameterError

__all__ = [
    'NONFINITE_PENALTY',
    'TRIM_CHI2',
    'TRIM_MAX_FRACTION',
    'BASE',
    'TwistSource',
    'ErrorFunction',
    'ParameterLayout',
    'check_sigma_diag',
    'whitening',
    'whiten',
    'whitened_residuals',
    'segment_losses',
    'solve',
    'trim_mask',
]

# Whitened units given to a non-finite error (far beyond any real one at the default Sigma).
NONFINITE_PENALTY = 1e6
# Outlier rule: whitened squared distance above TRIM_CHI2 times a robust scale, at most
# TRIM_MAX_FRACTION of the segments (the worst first).
TRIM_CHI2 = float(stats.chi2.ppf(0.999, 3))
TRIM_MAX_FRACTION = 0.1
# ``ParameterLayout.free`` entries of the base model carry this instead of an extension index.
BASE = -1

TwistSource = Union[BoundModel, BoundAugmented]
# How a fit scores a twist source: its end-pose errors (N, 3), true - predicted.
ErrorFunction = Callable[[TwistSource], np.ndarray]


def check_sigma_diag(sigma_diag: Sequence[float]) -> None:
    """Raise ParameterError unless ``sigma_diag`` is three finite variances > 0."""
    sigma = np.asarray(sigma_diag, dtype=float)
    if sigma.shape != (3,) or not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        raise ParameterError('sigma_diag must be three finite variances > 0 for (x [m^2], '
                             f'y [m^2], yaw [rad^2]), got {sigma_diag!r}')


def whitening(sigma_diag: Sequence[float]) -> np.ndarray:
    """Return W = diag(sigma_diag)^-1/2 as a vector (x, y, yaw)."""
    return 1.0 / np.sqrt(np.asarray(sigma_diag, dtype=float))


def whiten(errors: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Return W e for every segment: ``weight`` is a diagonal (3,) or matrices (N, 3, 3)."""
    weight = np.asarray(weight, dtype=float)
    if weight.ndim == 3:
        with np.errstate(invalid='ignore', over='ignore'):
            return np.einsum('nij,nj->ni', weight, errors)
    return errors * weight


def whitened_residuals(errors: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Return the flat whitened residuals, non-finite ones replaced by the penalty (step 4)."""
    white = whiten(errors, weight)
    return np.nan_to_num(white, nan=NONFINITE_PENALTY, posinf=NONFINITE_PENALTY,
                         neginf=-NONFINITE_PENALTY).ravel()


def segment_losses(errors: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Return each segment's whitened squared distance e^T Sigma^-1 e (penalty if non-finite)."""
    white = whiten(errors, weight)
    return np.nan_to_num((white ** 2).sum(axis=1), nan=NONFINITE_PENALTY,
                         posinf=NONFINITE_PENALTY)


@dataclass(frozen=True)
class ParameterLayout:
    """Which entries of the optimizer vector are which parameters: base model + extensions.

    ``base_k`` and ``ext_k`` hold every parameter's value (the fixed ones stay as they are);
    ``free`` lists the optimizer's entries as (``BASE`` or extension index, parameter index).
    """

    base_name: str
    geometry: Geometry
    extensions: tuple[str, ...]
    base_k: np.ndarray
    ext_k: tuple[np.ndarray, ...]
    free: tuple[tuple[int, int], ...]

    @classmethod
    def build(cls, base_name: str, geometry: Geometry, base_values: Mapping[str, float],
              ext_values: Mapping[str, Mapping[str, float]], extensions: Sequence[str],
              free_base: bool, free_ext: Mapping[str, Sequence[str]]) -> 'ParameterLayout':
        """Lay out a base model and extensions (missing values: defaults).

        ``free_base``: every base parameter is free; ``free_ext``: {extension: the names of its
        free parameters}, taken in spec order.
        """
        model = get_model(base_name)
        base_k = model.vector(base_values, geometry)
        ext_k = tuple(get_extension(n).vector(ext_values.get(n, {})) for n in extensions)
        free = [(BASE, j) for j in range(len(model.params))] if free_base else []
        for i, name in enumerate(extensions):
            wanted = free_ext.get(name, ())
            free += [(i, j) for j, pname in enumerate(get_extension(name).param_names)
                     if pname in wanted]
        return cls(base_name, geometry, tuple(extensions), base_k, ext_k, tuple(free))

    @classmethod
    def of_model(cls, base_name: str, geometry: Geometry) -> 'ParameterLayout':
        """Lay out a plain model with every parameter free, at its defaults."""
        return cls.build(base_name, geometry, {}, {}, (), True, {})

    def specs(self) -> tuple[ParamSpec, ...]:
        """Return the spec of each free entry, in vector order."""
        base_specs = get_model(self.base_name).params
        return tuple(base_specs[j] if i == BASE else get_extension(self.extensions[i]).params[j]
                     for i, j in self.free)

    def vector(self) -> np.ndarray:
        """Return the current values of the free entries."""
        return np.array([self.base_k[j] if i == BASE else self.ext_k[i][j] for i, j in self.free])

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Return the free entries' optimizer bounds, (lower, upper), from their specs."""
        pairs = [spec.optimizer_bounds() for spec in self.specs()]
        return np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])

    def parameters(self, vector: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
        """Return (base k, extension k's) with the free entries set from ``vector``."""
        base_k = self.base_k.copy()
        ext_k = [k.copy() for k in self.ext_k]
        for value, (i, j) in zip(vector, self.free):
            if i == BASE:
                base_k[j] = value
            else:
                ext_k[i][j] = value
        return base_k, tuple(ext_k)

    def source(self, vector: np.ndarray) -> TwistSource:
        """Return the twist source the vector describes (unvalidated: bounds already hold)."""
        base_k, ext_k = self.parameters(vector)
        base = BoundModel(get_model(self.base_name), self.geometry, base_k)
        if not self.extensions:
            return base
        return BoundAugmented(base, self.extensions, ext_k)

    def values(self, vector: np.ndarray) -> tuple[dict[str, float], dict[str, dict[str, float]]]:
        """Return ({base parameter: value}, {extension: {parameter: value}}) for ``vector``."""
        base_k, ext_k = self.parameters(vector)
        return (get_model(self.base_name).mapping(base_k),
                {name: get_extension(name).mapping(k) for name, k in zip(self.extensions, ext_k)})


def solve(errors: ErrorFunction, layout: ParameterLayout, weight: np.ndarray,
          x0: np.ndarray | None = None, max_nfev: int = 60, loss: str = 'linear',
          f_scale: float = 1.0, jacobian: Callable[[TwistSource], np.ndarray] | None = None
          ) -> optimize.OptimizeResult:
    """Minimise the whitened errors over the layout's free entries (module docstring).

    ``x0``: the start (default: the layout's current values), clipped into the bounds.
    ``max_nfev``: evaluations per free parameter (plus one). ``jacobian``: the errors' exact
    derivatives (N, 3, P) with respect to the free entries, for a source (default: scipy's
    finite differences, one evaluation per free entry). The result is scipy's; without a
    free parameter it holds the evaluation only (``x`` empty, ``fun`` and ``cost``).
    """
    x0 = layout.vector() if x0 is None else np.asarray(x0, dtype=float)

    def residuals(vector: np.ndarray) -> np.ndarray:
        return whitened_residuals(errors(layout.source(vector)), weight)

    def whitened_jacobian(vector: np.ndarray) -> np.ndarray:
        jac = jacobian(layout.source(vector))
        white = np.asarray(weight, dtype=float)
        if white.ndim == 3:
            jac = np.einsum('nij,njp->nip', white, jac)
        else:
            jac = jac * white[None, :, None]
        return np.nan_to_num(jac, nan=0.0, posinf=0.0, neginf=0.0).reshape(-1, x0.size)

    if x0.size == 0:
        fun = residuals(x0)
        return optimize.OptimizeResult(x=x0, fun=fun, cost=float(0.5 * fun @ fun),
                                       jac=np.zeros((fun.size, 0)), success=True, nfev=1,
                                       message='no free parameter: evaluated only')
    lo, hi = layout.bounds()
    x0 = np.clip(x0, lo, hi)
    return optimize.least_squares(residuals, x0,
                                  jac='2-point' if jacobian is None else whitened_jacobian,
                                  bounds=(lo, hi), loss=loss, f_scale=f_scale,
                                  x_scale='jac', max_nfev=max_nfev * (x0.size + 1),
                                  method='trf')


def trim_mask(errors: np.ndarray, weight: np.ndarray, chi2_factor: float = TRIM_CHI2,
              max_fraction: float = TRIM_MAX_FRACTION) -> np.ndarray:
    """Return True for segments kept after trimming outliers (C15).

    A segment is an outlier when its whitened squared distance exceeds ``chi2_factor`` times a
    robust scale (median of the distances / median of chi2 with 3 dof); at most
    ``max_fraction`` of them are dropped, the worst first.
    """
    dist2 = (whiten(errors, weight) ** 2).sum(axis=1)
    scale = np.median(dist2) / stats.chi2.median(3)
    if not scale > 0:
        return np.ones(dist2.shape, bool)
    outlier = dist2 > chi2_factor * scale
    max_drop = int(math.floor(max_fraction * dist2.size))
    if outlier.sum() > max_drop:
        worst = np.argsort(-dist2, kind='stable')[:max_drop]
        outlier = np.zeros(dist2.shape, bool)
        outlier[worst] = True
    return ~outlier
