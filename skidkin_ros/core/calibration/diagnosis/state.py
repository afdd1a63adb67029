"""A model under diagnosis: its structure and values, and how it is fitted on segments.

A :class:`ModelState` is a base model's values plus extensions with theirs. ``found`` lists the
extensions the diagnosis added; an extension in the structure but not found (the stamp
convention's time offset) is a fixed part of the baseline, never refitted.

:func:`fit_state` fits a state with the one engine (:mod:`skidkin_ros.core.calibration.engine`):
the base parameters (with ``refit_base``) and each found extension's fitted parameters are free
(a library extension's: its chosen terms; a grid-searched parameter only when the extension
refines it), scored by the :class:`SegmentPredictor`'s end-pose errors, because augmented models
carry state along a whole drive.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from skidkin_ros.core.calibration.diagnosis.options import DiagnosisOptions
from skidkin_ros.core.calibration.engine import (ParameterLayout, segment_losses, solve,
                                                 TwistSource)
from skidkin_ros.core.calibration.predictor import SegmentPredictor
from skidkin_ros.core.kinematics.augmented import AugmentedModel
from skidkin_ros.core.kinematics.extensions import get_extension
from skidkin_ros.core.kinematics.models import BoundModel, get_model
from skidkin_ros.core.kinematics.specs import Geometry

__all__ = ['ModelState', 'layout_of', 'fit_state', 'held_out_loss']

# Fits of two or more parameters use the predictor's exact Jacobian (forward mode, about two
# evaluations' cost); False: scipy's finite differences (one rollout per free parameter and
# iteration), kept for comparisons.
ANALYTIC_JACOBIAN = True


@dataclass(frozen=True)
class ModelState:
    """A structure with its values: base values and {extension: {param: value}}.

    ``sparse_terms``: the library terms a library extension uses; ``found``: the extensions the
    diagnosis added (fitted), in the order they were found; ``residual_covariance``: the
    residual model's coefficient covariance, row-major (empty: none).
    """

    extensions: tuple[str, ...]
    base_values: dict[str, float]
    ext_values: dict[str, dict[str, float]]
    sparse_terms: tuple[str, ...] = ()
    found: tuple[str, ...] = ()
    residual_covariance: tuple[float, ...] = ()

    def terms(self, name: str) -> tuple[str, ...]:
        """Return the terms a learned extension uses (library: chosen; regression: non-zero)."""
        ext = get_extension(name)
        if ext.library:
            return self.sparse_terms
        if ext.regression:
            return tuple(p for p, v in self.ext_values.get(name, {}).items()
                         if p.startswith(('vx_', 'vy_', 'wz_')) and v != 0.0)
        return ()

    def bind(self, base_name: str, geometry: Geometry) -> TwistSource:
        model = get_model(base_name)
        base = BoundModel(model, geometry, model.vector(self.base_values, geometry))
        if not self.extensions:
            return base
        return AugmentedModel(base_name, self.extensions).bind(base, self.ext_values)

    def shown_values(self, name: str) -> dict[str, float]:
        """Return what a report shows of a found extension: fitted and scanned, or its terms."""
        ext = get_extension(name)
        values = self.ext_values.get(name, {})
        shown = self.terms(name) if ext.learned else ext.fitted + ext.scan
        return {param: values[param] for param in shown if param in values}


def layout_of(base_name: str, geometry: Geometry, state: ModelState, refit_base: bool,
              fixed: Sequence[str] = ()) -> ParameterLayout:
    """Return the engine's layout of a state; ``fixed`` names 'extension.parameter's kept."""
    free = {}
    for name in state.extensions:
        if name not in state.found:
            continue  # a structural part (the stamp convention): kept as it is
        ext = get_extension(name)
        wanted = state.sparse_terms if ext.library else ext.fitted
        free[name] = tuple(p for p in ext.param_names
                           if p in wanted and f'{name}.{p}' not in fixed
                           and (p not in ext.scan or ext.refine))
    return ParameterLayout.build(base_name, geometry, state.base_values, state.ext_values,
                                 state.extensions, refit_base, free)


def fit_state(predictor: SegmentPredictor, base_name: str, geometry: Geometry,
              state: ModelState, options: DiagnosisOptions, keep: np.ndarray | None = None,
              refit_base: bool | None = None, fixed: Sequence[str] = ()
              ) -> tuple[ModelState, float]:
    """Fit the free parameters on the (kept) segments; return (fitted state, cost).

    A state without a free parameter is returned as it is, with its cost.
    """
    refit = options.refit_base if refit_base is None else refit_base
    layout = layout_of(base_name, geometry, state, refit, fixed)

    def errors(source: TwistSource) -> np.ndarray:
        return predictor.errors(source, keep)

    offset = [c for c, (i, j) in enumerate(layout.free)
              if i >= 0 and get_extension(layout.extensions[i]).stage == 'timing']

    def jacobian(source: TwistSource) -> np.ndarray:
        return predictor.errors_jacobian(source, layout.free, offset[0] if offset else None,
                                         keep)

    # one free parameter: a finite difference costs one evaluation, less than the exact slope
    exact = ANALYTIC_JACOBIAN and len(layout.free) >= 2
    sol = solve(errors, layout, options.whitening, max_nfev=options.max_nfev,
                jacobian=jacobian if exact else None)
    if not layout.free:
        return state, sol.cost
    base_values, ext_values = layout.values(sol.x)
    return (ModelState(state.extensions, base_values, ext_values, state.sparse_terms,
                       state.found, state.residual_covariance), float(sol.cost))


def held_out_loss(predictor: SegmentPredictor, source: TwistSource, options: DiagnosisOptions,
                  keep: np.ndarray | None = None) -> np.ndarray:
    """Return the per-segment whitened squared end-pose errors of the (kept) segments."""
    return segment_losses(predictor.errors(source, keep), options.whitening)
