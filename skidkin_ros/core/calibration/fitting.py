"""Fit the kinematic models on segments, as in Baril et al. 2020 (section "Experimental setup").

Loss: the sum over segments of squared Mahalanobis distances between the ground-truth and the
predicted end pose, l(k) = sum_i e_i^T Sigma^-1 e_i, each prediction starting from the segment's
ground-truth start pose. e_i is expressed in the segment's start (body) frame (longitudinal,
lateral, heading; heading wrapped), so a non-isotropic Sigma means something; with the default
identity Sigma this equals the paper's world-frame loss. Sigma brings metres and radians to one
unitless scale.

The optimizer is the one engine of :mod:`skidkin_ros.core.calibration.engine` (scipy's bounded
``least_squares`` on the whitened residuals W e_i, W^T W = Sigma^-1, bounds from each ParamSpec)
with an optional robust loss (``soft_l1``, ``huber``, ``cauchy``... with ``f_scale`` in whitened
units). All segments are rolled out at once (one vectorized call of the shared integrator per cost
evaluation).

Outlier trimming (C15): after a first fit, segments whose whitened squared distance exceeds
``trim_chi2`` times a robust scale are dropped (at most ``trim_max_fraction`` of them, the worst
first: :func:`skidkin_ros.core.calibration.engine.trim_mask`) and the model is refitted once.

Several starts (C20: seeded, so the same input gives the same output) for models with at least
``multi_start_min_params`` parameters: the default start plus random starts drawn around it.

Diagnostics: standard errors from the Jacobian at the solution and the residual variance,
cov = s^2 (J^T J)^-1, s^2 = sum(r^2) / (m - p) (with a robust loss, scipy's modified Jacobian
and the robust cost are used: an approximation); non-observable parameters (C14) from a lack of
turning / translation in the data and from the Jacobian's near-null space; parameters on a bound
and non-converged fits (C16) make the fit invalid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import logging
import math
import time
from typing import Sequence

import numpy as np
from scipy import optimize

from skidkin_ros.core.calibration.engine import (check_sigma_diag, ParameterLayout, solve,
                                                 TRIM_CHI2, trim_mask, TRIM_MAX_FRACTION,
                                                 TwistSource, whitening)
from skidkin_ros.core.calibration.segments import segment_frame_error, SegmentSet
from skidkin_ros.core.kinematics.augmented_tangents import base_tangents
from skidkin_ros.core.kinematics.models import BoundModel, get_model, KinematicModel, MODEL_NAMES
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.se2 import rollout_columns
from skidkin_ros.core.odometry.se2_tangent import window_tangents
from skidkin_ros.errors import DataError, ParameterError

__all__ = [
    'FitOptions',
    'Excitation',
    'FitResult',
    'predict_end_poses',
    'segment_errors',
    'segment_errors_jacobian',
    'measure_excitation',
    'parameter_scales',
    'solve_model',
    'assess_fit',
    'fit_model',
    'fit_models',
]

LOG = logging.getLogger(__name__)

# Fits of three or more parameters use the exact Jacobian of the segment errors (forward mode,
# about three rollouts' cost); one or two free parameters keep scipy's finite difference (one
# rollout each: edd_symmetric's fit is 8 % cheaper so). False: finite differences everywhere
# (the comparison the tests make).
EXACT_JACOBIAN = True
EXACT_JACOBIAN_MIN_PARAMS = 3

ROBUST_LOSSES = ('linear', 'soft_l1', 'huber', 'cauchy', 'arctan')

# Parameters that only turning reveals / that only translation reveals, per model (C14).
NEEDS_TURNING: dict[str, tuple[str, ...]] = {
    'edd_symmetric': ('b_hat',),
    'edd_asymmetric': ('x_v', 'y_l', 'y_r'),
    'roc': ('beta_1', 'beta_2'),
    'full_linear': ('gamma_11', 'gamma_12', 'gamma_21', 'gamma_22', 'gamma_31', 'gamma_32'),
}
NEEDS_TRANSLATION: dict[str, tuple[str, ...]] = {
    'edd_symmetric': ('alpha', 'b_hat'),
    'edd_asymmetric': ('alpha_l', 'alpha_r', 'x_v', 'y_l', 'y_r'),
    'roc': ('alpha', 'beta_1', 'beta_2'),
    'full_linear': ('gamma_11', 'gamma_12', 'gamma_21', 'gamma_22', 'gamma_31', 'gamma_32'),
}


@dataclass(frozen=True)
class FitOptions:
    """Options of the least-squares fit (see the module docstring)."""

    sigma_diag: tuple[float, float, float] = (1.0, 1.0, 1.0)
    loss: str = 'linear'
    f_scale: float = 1.0
    trim: bool = True
    trim_chi2: float = TRIM_CHI2
    trim_max_fraction: float = TRIM_MAX_FRACTION
    n_starts: int = 8
    multi_start_min_params: int = 3
    seed: int = 0
    max_nfev: int = 60
    screen_segments: int = 100
    screen_max_nfev: int = 12
    min_turning_segments: int = 3
    min_turn_rad: float = 0.15
    min_translating_segments: int = 3
    min_translation_m: float = 0.3
    null_space_tol: float = 1e-6
    max_relative_se: float = 1.0

    def __post_init__(self) -> None:
        if self.loss not in ROBUST_LOSSES:
            raise ParameterError(f'loss must be one of {ROBUST_LOSSES}, got {self.loss!r}')
        check_sigma_diag(self.sigma_diag)
        if not (self.f_scale > 0 and math.isfinite(self.f_scale)):
            raise ParameterError(f'f_scale must be > 0 (whitened units), got {self.f_scale!r}')
        if not 0.0 <= self.trim_max_fraction < 1.0:
            raise ParameterError('trim_max_fraction must be in [0, 1), '
                                 f'got {self.trim_max_fraction!r}')
        if self.n_starts < 1:
            raise ParameterError(f'n_starts must be >= 1, got {self.n_starts!r}')

    @property
    def whitening(self) -> np.ndarray:
        return whitening(self.sigma_diag)


@dataclass(frozen=True)
class Excitation:
    """How much the training segments turn and translate (decides observability, C14)."""

    segments: int
    turning_segments: int
    translating_segments: int
    total_rotation_rad: float
    total_path_m: float

    def missing(self, options: FitOptions) -> list[str]:
        gaps = []
        if self.turning_segments < options.min_turning_segments:
            gaps.append('turning')
        if self.translating_segments < options.min_translating_segments:
            gaps.append('translation')
        return gaps


@dataclass(frozen=True)
class FitResult:
    """One model fitted on one set of segments."""

    model: str
    values: dict[str, float]
    std_errors: dict[str, float]
    cost: float
    rms_error: tuple[float, float, float]
    segments_used: int
    segments_trimmed: int
    converged: bool
    status: str
    starts: int
    on_bound: tuple[str, ...] = ()
    # on a lower bound that is part of the model (a valid constrained minimum: roc's beta_2 = 0)
    at_constraint: tuple[str, ...] = ()
    unobservable: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    seconds: float = 0.0
    trimmed_mask: np.ndarray = field(default=None, repr=False)
    # s^2 (J^T J)^-1 in the order of the model's parameters (the std_errors are its diagonal)
    covariance: np.ndarray | None = field(default=None, repr=False)
    weighting: str = 'fixed'
    iterations: int = 0

    @property
    def valid(self) -> bool:
        """Tell whether the fit converged, is off its bounds and observable (C14/C16)."""
        return self.converged and not self.on_bound and not self.unobservable


def predict_end_poses(model: KinematicModel, k: np.ndarray, geometry: Geometry,
                      segments: SegmentSet) -> np.ndarray:
    """End pose (N, 3) predicted by the model for every segment, from its true start pose."""
    end = np.empty((len(segments), 3))
    for idx, width in segments.batches():
        omega_l = segments.omega_l[idx, :width]
        omega_r = segments.omega_r[idx, :width]
        v_x, v_y, omega = model.twist_components(k, geometry, omega_l, omega_r)
        x, y, yaw = rollout_columns(v_x, v_y, omega, segments.dt_s[idx, :width],
                                    segments.start[idx])
        end[idx, 0], end[idx, 1], end[idx, 2] = x[:, -1], y[:, -1], yaw[:, -1]
    return end


def segment_errors(model: KinematicModel, k: np.ndarray, geometry: Geometry,
                   segments: SegmentSet) -> np.ndarray:
    """End-pose errors (N, 3) in each segment's start frame (true - predicted, yaw wrapped)."""
    predicted = predict_end_poses(model, k, geometry, segments)
    return segment_frame_error(segments.start, segments.end, predicted)


def segment_errors_jacobian(model: KinematicModel, k: np.ndarray, geometry: Geometry,
                            segments: SegmentSet) -> np.ndarray:
    """Return the exact derivatives (N, 3, p) of :func:`segment_errors` (0 where not finite).

    Forward mode, the diagnosis's own tangents: d twist / d k
    (:func:`~skidkin_ros.core.kinematics.augmented_tangents.base_tangents`) carried through each
    segment's rollout from the origin
    (:func:`~skidkin_ros.core.odometry.se2_tangent.window_tangents`, one window per segment).
    The error is true - start * T in the start frame, so its derivative is -dT: about three
    rollouts' cost for any number of parameters, where a finite difference takes one rollout
    per parameter.
    """
    k = np.asarray(k, dtype=float)
    free = [(-1, j) for j in range(k.size)]
    bound = BoundModel(model, geometry, k)
    jac = np.zeros((len(segments), 3, k.size))
    for idx, width in segments.batches():
        count = idx.size
        # one more stamp per row: window_tangents leaves the step after the last stamp out
        omega_l, omega_r, dt_s = (np.zeros((count, width + 1)) for _ in range(3))
        omega_l[:, :width] = segments.omega_l[idx, :width]
        omega_r[:, :width] = segments.omega_r[idx, :width]
        dt_s[:, :width] = segments.dt_s[idx, :width]
        with np.errstate(all='ignore'):
            twist = model.twist_components(k, geometry, omega_l, omega_r)
            d_twist = base_tangents(bound, omega_l, omega_r, free)
            first = np.arange(count, dtype=np.int64) * (width + 1)
            last = first + width
            poses, (u_x, u_y, turn) = window_tangents(*twist, dt_s, *d_twist, first, last)
            end_x, end_y = poses[0][last], poses[1][last]
            jac[idx, 0] = -(u_x - end_y * turn).T
            jac[idx, 1] = -(u_y + end_x * turn).T
            jac[idx, 2] = -turn.T
    jac[~np.isfinite(jac)] = 0.0
    return jac


def measure_excitation(segments: SegmentSet, options: FitOptions) -> Excitation:
    """Count segments that turn (|rotation| >= min_turn_rad) and that translate.

    Translation is the straight-line displacement between the segment's ends (>=
    min_translation_m), not the path length: ground-truth noise adds path length even to a spin
    in place.
    """
    rotation = np.abs(segments.rotation_rad)
    chord = np.hypot(*(segments.end[:, :2] - segments.start[:, :2]).T)
    return Excitation(len(segments), int((rotation >= options.min_turn_rad).sum()),
                      int((chord >= options.min_translation_m).sum()),
                      float(rotation.sum()), float(segments.path_m.sum()))


def parameter_scales(model: KinematicModel, geometry: Geometry) -> np.ndarray:
    """Typical magnitude of each parameter (for start draws and relative uncertainty)."""
    unit_scale = {'m': geometry.track_width, 'm/rad': geometry.wheel_radius,
                  '-': 1.0}
    scales = []
    for spec in model.params:
        default = abs(spec.default_for(geometry))
        scales.append(max(default, unit_scale.get(spec.unit, 1.0) * 0.5))
    return np.array(scales)


def _starts(model: KinematicModel, geometry: Geometry, options: FitOptions,
            rng: np.random.Generator) -> list[np.ndarray]:
    x0 = model.vector({}, geometry)
    starts = [x0]
    if len(model.params) < options.multi_start_min_params:
        return starts
    lo, hi = ParameterLayout.of_model(model.name, geometry).bounds()
    scales = parameter_scales(model, geometry)
    for _ in range(options.n_starts - 1):
        draw = x0 + rng.uniform(-0.5, 0.5, size=x0.size) * scales
        starts.append(np.clip(draw, lo + 1e-3 * scales, hi - 1e-3 * scales))
    return starts


def solve_model(model: KinematicModel, geometry: Geometry, segments: SegmentSet,
                options: FitOptions, x0: np.ndarray, max_nfev: int | None = None,
                weight: np.ndarray | None = None) -> optimize.OptimizeResult:
    """Fit every parameter of the model from ``x0`` with the engine (plain rollout errors).

    ``weight``: the whitening, a diagonal (3,) or one matrix per segment (N, 3, 3); default
    the options' fixed Sigma.
    """
    def errors(source: TwistSource) -> np.ndarray:
        return segment_errors(model, source.k, geometry, segments)

    def jacobian(source: TwistSource) -> np.ndarray:
        return segment_errors_jacobian(model, source.k, geometry, segments)

    weight = options.whitening if weight is None else weight
    exact = EXACT_JACOBIAN and len(model.params) >= EXACT_JACOBIAN_MIN_PARAMS
    return solve(errors, ParameterLayout.of_model(model.name, geometry), weight, x0,
                 max_nfev or options.max_nfev, options.loss, options.f_scale,
                 jacobian=jacobian if exact else None)


def _best_solution(model: KinematicModel, geometry: Geometry, segments: SegmentSet,
                   options: FitOptions) -> tuple[optimize.OptimizeResult, int, bool]:
    """Best start, solved on a deterministic subsample when the data are large.

    Returns (solution, number of starts, whether the solution is on the whole set). The caller
    trims with it and refines once on everything: one full solve instead of two.
    """
    rng = np.random.default_rng(options.seed)
    starts = _starts(model, geometry, options, rng)
    screen = segments
    if len(segments) > options.screen_segments:
        pick = np.linspace(0, len(segments) - 1, options.screen_segments).round().astype(int)
        screen = segments.subset(np.unique(pick))
    # Screening only has to rank the starts: a start still wandering after a few iterations
    # is not the best one, so screening solves are capped; the winner is refined in full.
    cap = options.screen_max_nfev if len(starts) > 1 else None
    best = None
    for x0 in starts:
        sol = solve_model(model, geometry, screen, options, x0, cap)
        if best is None or sol.cost < best.cost - 1e-12 * max(1.0, best.cost):
            best = sol
    if cap is not None and screen is segments:
        best = solve_model(model, geometry, segments, options, best.x)
    return best, len(starts), screen is segments


def _parameter_covariance(sol: optimize.OptimizeResult, n_params: int) -> np.ndarray:
    """Return s^2 (J^T J)^-1 at the solution (module docstring), symmetric."""
    m = sol.fun.size
    dof = max(m - n_params, 1)
    s2 = 2.0 * sol.cost / dof
    jtj = sol.jac.T @ sol.jac
    cov = np.linalg.pinv(jtj) * s2
    return 0.5 * (cov + cov.T)


def _null_space_params(model: KinematicModel, geometry: Geometry, jac: np.ndarray,
                       tol: float) -> set[str]:
    """Parameters involved in near-null directions of the column-scaled Jacobian."""
    scaled = jac * parameter_scales(model, geometry)
    norms = np.linalg.norm(scaled, axis=0)
    names = set()
    top = norms.max() if norms.size else 0.0
    if top == 0.0:
        return set(model.param_names)
    for i, norm in enumerate(norms):
        if norm <= tol * top:
            names.add(model.param_names[i])
    _, sv, vt = np.linalg.svd(scaled, full_matrices=False)
    for value, vector in zip(sv, vt):
        if value <= tol * sv[0]:
            for i in np.nonzero(np.abs(vector) > 0.3)[0]:
                names.add(model.param_names[i])
    return names


def _ideal_result(model: KinematicModel, geometry: Geometry, segments: SegmentSet,
                  options: FitOptions) -> FitResult:
    err = segment_errors(model, np.zeros(0), geometry, segments)
    white = err * options.whitening
    return FitResult(model.name, {}, {}, float(0.5 * (white ** 2).sum()),
                     tuple(float(v) for v in np.sqrt((err ** 2).mean(axis=0))), len(segments), 0,
                     True, 'no parameter: evaluated only', 0,
                     trimmed_mask=np.zeros(len(segments), bool))


def fit_model(name: str, geometry: Geometry, segments: SegmentSet,
              options: FitOptions | None = None) -> FitResult:
    """Fit one model on the segments (ideal_dd, without parameters, is only evaluated)."""
    options = options or FitOptions()
    model = get_model(name)
    if len(segments) < max(len(model.params) + 1, 2):
        raise DataError(f'{len(segments)} training segment(s) are too few to fit {name!r} '
                        f'({len(model.params)} parameters); drive more or shorten h_t')
    tic = time.perf_counter()
    if not model.params:
        return _ideal_result(model, geometry, segments, options)
    sol, n_starts, on_all = _best_solution(model, geometry, segments, options)
    used = segments
    kept = np.ones(len(segments), bool)
    if options.trim:
        kept = trim_mask(segment_errors(model, sol.x, geometry, segments), options.whitening,
                         options.trim_chi2, options.trim_max_fraction)
        if not kept.all():
            used = segments.subset(kept)
            on_all = False
    if not on_all:
        sol = solve_model(model, geometry, used, options, sol.x)
    trimmed = int((~kept).sum())
    return assess_fit(model, geometry, used, options, sol, n_starts, trimmed, kept,
                      time.perf_counter() - tic)


def assess_fit(model: KinematicModel, geometry: Geometry, used: SegmentSet,
               options: FitOptions, sol: optimize.OptimizeResult, n_starts: int,
               trimmed: int, kept: np.ndarray, seconds: float, weighting: str = 'fixed'
               ) -> FitResult:
    """Turn a solution into a FitResult: standard errors, bounds, observability, convergence."""
    names = model.param_names
    param_cov = _parameter_covariance(sol, len(names))
    se = np.sqrt(np.clip(np.diag(param_cov), 0.0, None))
    warnings = []
    specs = model.params
    on_bound = tuple(spec.name for spec, value in zip(specs, sol.x) if spec.on_bound(value))
    if on_bound:
        ranges = ', '.join(f'{s.name} fitted in {s.fit_range_text()}' for s in specs
                           if s.name in on_bound)
        warnings.append(f'{model.name}: parameter(s) {", ".join(on_bound)} sit on a bound '
                        f'({ranges}): the data want a value outside the model; the fit is '
                        'marked invalid')
    at_constraint = tuple(spec.name for spec, value in zip(specs, sol.x)
                          if spec.at_constraint(value))
    unobservable = set(_null_space_params(model, geometry, sol.jac, options.null_space_tol))
    excitation = measure_excitation(used, options)
    for gap in excitation.missing(options):
        if gap == 'turning':
            params = NEEDS_TURNING.get(model.name, ())
            have, need = excitation.turning_segments, options.min_turning_segments
            remedy = f'turns and spins (|rotation| >= {options.min_turn_rad:g} rad per segment)'
        else:
            params = NEEDS_TRANSLATION.get(model.name, ())
            have, need = excitation.translating_segments, options.min_translating_segments
            remedy = f'straight and curved paths (>= {options.min_translation_m:g} m per segment)'
        unobservable.update(params)
        if params:
            warnings.append(
                f'{model.name}: not enough {gap} in the training data ({have} of '
                f'{excitation.segments} segments, need {need}): {", ".join(params)} cannot be '
                f'observed; drive {remedy}')
    scales = parameter_scales(model, geometry)
    vague = [n for n, s, sc in zip(names, se, scales) if s > options.max_relative_se * sc]
    if vague:
        unobservable.update(vague)
        warnings.append(f'{model.name}: standard error of {", ".join(vague)} exceeds '
                        f'{options.max_relative_se:g}x its typical magnitude: not determined '
                        'by the data')
    ordered = tuple(n for n in names if n in unobservable)
    if ordered and not any('cannot be observed' in w or 'standard error' in w for w in warnings):
        warnings.append(f'{model.name}: parameter(s) {", ".join(ordered)} are not observable '
                        '(near-null direction of the fit Jacobian)')
    converged = bool(sol.success) and bool(np.all(np.isfinite(sol.x)))
    if not converged:
        warnings.append(f'{model.name}: optimizer did not converge ({sol.message})')
    err = segment_errors(model, sol.x, geometry, used)
    return FitResult(
        model=model.name, values=model.mapping(sol.x),
        std_errors={n: float(s) for n, s in zip(names, se)},
        cost=float(sol.cost), rms_error=tuple(float(v) for v in np.sqrt((err ** 2).mean(0))),
        segments_used=len(used), segments_trimmed=trimmed, converged=converged,
        status=str(sol.message), starts=n_starts, on_bound=on_bound, at_constraint=at_constraint,
        unobservable=ordered,
        warnings=tuple(warnings), seconds=seconds, trimmed_mask=~kept, covariance=param_cov,
        weighting=weighting)


def fit_models(geometry: Geometry, segments: SegmentSet,
               options: FitOptions | None = None,
               models: Sequence[str] = MODEL_NAMES) -> dict[str, FitResult]:
    """Fit every requested model (all five by default) on the same segments."""
    options = options or FitOptions()
    results = {}
    for name in models:
        result = fit_model(name, geometry, segments, options)
        LOG.info('fitted %s on %d segments in %.2f s (cost %.4g, valid %s)', name,
                 result.segments_used, result.seconds, result.cost, result.valid)
        results[name] = result
    return results
