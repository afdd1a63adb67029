"""Diagnose what a calibrated model misses, add it as extensions, measure before and after.

``diagnose(train, evaluate, geometry, base_values_by_model, base_model_name, options)``:

1. **Residuals.** Ground-truth body velocities come from a smoothing differentiator: on the fresh
   ground-truth poses only (sample-and-hold duplicates dropped), a local quadratic is fitted to x,
   y and yaw in a window of +-``smoothing_s`` around each pose and differentiated there; the
   model's poses at the same stamps go through the same differentiator, so both are smoothed
   alike. Residual = ground truth - model, per pose, in the body frame (v_x, v_y, omega); and per
   training segment, the end-pose error.
2. **Trace.** The residuals are correlated with every signal the data offers (wheel speeds, sum,
   difference, ratio, their time derivatives, body speed, yaw rate, curvature, v omega, direction,
   time in drive, position, IMU yaw rate) and the wheel-vs-ground-truth lag is found by refitting
   the velocity residual over a range of offsets.
3. **Candidates.** Every named extension (and the sparse fallback: STLSQ on the per-pose
   residuals over a library of twist terms, then the chosen terms only) is fitted on segments by
   bounded least squares, like :mod:`skidkin_ros.core.calibration.fitting`, with the base model's
   parameters refitted jointly (``refit_base``; the file then holds the joint values for the base
   model). Step-like parameters (the terrain switch time) are searched on a grid first. With
   ``trim`` the outlier training segments of the base refit are dropped once, as calibration does;
   off by default, because the segments a missing effect hits hardest look like outliers to the
   base model (a yaw slip at one speed ratio, fast driving) and trimming them hides the effect.
4. **Selection.** Cross-validation over ``folds`` groups of training segments (by ``calib_step``
   when the drives carry one, by drive when there are enough, else interleaved time blocks): each
   candidate's held-out loss (whitened squared end-pose error) against the current model's.
   Parsimony: a candidate is accepted only when it lowers the held-out loss by more than
   ``min_relative_gain`` AND a one-sided Wilcoxon signed-rank test of the per-segment differences
   gives p < ``significance``. Greedy forward selection, at most ``max_extensions``; the sparse
   fallback is tried only when no named extension passes, at every STLSQ threshold of
   ``sparse_thresholds``, and the variant with the fewest terms whose held-out loss is not
   significantly above the best one's is the one scored. The fits of a round are independent
   tasks, run on ``jobs`` processes (:mod:`skidkin_ros.core.parallel`).
5. **Before/after.** eps_t and eps_theta on the evaluation drives (a deterministic hold-out when
   none are given) for the base model as given, refitted, and after each accepted extension.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
import logging
import math
import time
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy import optimize, stats

from skidkin_ros import __version__
from skidkin_ros.core.calibration.engine import trim_mask
from skidkin_ros.core.calibration.evaluation import ErrorStats, relative_errors
from skidkin_ros.core.calibration.holdout import resolve_holdout
from skidkin_ros.core.calibration.predictor import SegmentPredictor
from skidkin_ros.core.calibration.segments import HorizonOptions, SegmentSet, usable_segments
from skidkin_ros.core.drive import Drive, fresh_pose_mask
from skidkin_ros.core.kinematics.augmented import AUGMENTED_NAME, AugmentedModel, BoundAugmented
from skidkin_ros.core.kinematics.extensions import (EXTENSION_NAMES, get_extension, ordered,
                                                    SPARSE_FEATURES, sparse_features)
from skidkin_ros.core.kinematics.models import BoundModel, get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.integrator import rollout_stream
from skidkin_ros.core.parallel import fork_map
from skidkin_ros.errors import DataError, ParameterError

__all__ = ['DiagnosisOptions', 'DiagnosisResult', 'CandidateScore', 'ModelStep', 'Trace',
           'diagnose', 'truth_velocities', 'body_velocities', 'stlsq']

LOG = logging.getLogger(__name__)
NAMED = tuple(n for n in EXTENSION_NAMES if n != 'sparse_correction')
SPARSE = 'sparse_correction'
# Two passing candidates whose held-out losses differ with p >= this are called a tie.
TIE_SIGNIFICANCE = 0.05
# progress(round, fits done, fits in the round): how a caller follows a long selection.
Progress = Callable[[int, int, int], None]


@dataclass(frozen=True)
class DiagnosisOptions(HorizonOptions):
    """Everything that shapes a diagnosis (saved with the results as provenance)."""

    candidates: tuple[str, ...] = EXTENSION_NAMES
    refit_base: bool = True
    folds: int = 3
    min_relative_gain: float = 0.05
    significance: float = 0.01
    max_extensions: int = 3
    max_nfev: int = 30
    smoothing_s: float = 0.35
    lag_range_s: float = 0.4
    sparse_thresholds: tuple[float, ...] = (0.1, 0.2, 0.4)
    scan_points: int = 12
    holdout_every: int = 3
    holdout_mode: str = 'auto'
    holdout_block_s: float = 60.0
    holdout_key: str | None = None
    max_dt_s: float = 0.5
    stamp_convention: str = 'mid'
    trim: bool = False

    def __post_init__(self) -> None:
        ordered(self.candidates)
        if self.stamp_convention not in ('mid', 'start'):
            raise ParameterError("stamp_convention must be 'mid' (wheel speeds describe the "
                                 "middle of the interval they are held over) or 'start', got "
                                 f'{self.stamp_convention!r}')
        if self.folds < 2:
            raise ParameterError(f'folds must be >= 2, got {self.folds!r}')
        if not 0.0 <= self.min_relative_gain < 1.0:
            raise ParameterError('min_relative_gain must be in [0, 1) (fraction of held-out '
                                 f'loss), got {self.min_relative_gain!r}')
        if not 0.0 < self.significance < 1.0:
            raise ParameterError(f'significance must be in (0, 1), got {self.significance!r}')
        sigma = np.asarray(self.sigma_diag, dtype=float)
        if sigma.shape != (3,) or np.any(~np.isfinite(sigma)) or np.any(sigma <= 0):
            raise ParameterError('sigma_diag must be three variances > 0 (m^2, m^2, rad^2)')
        if (not self.sparse_thresholds
                or not all(isinstance(t, (int, float)) and t > 0 for t in self.sparse_thresholds)):
            raise ParameterError('sparse_thresholds must be one or more coefficient thresholds '
                                 f'> 0, got {self.sparse_thresholds!r}')
        if not self.smoothing_s > 0:
            raise ParameterError(f'smoothing_s must be > 0 s, got {self.smoothing_s!r}')

    @property
    def whitening(self) -> np.ndarray:
        return 1.0 / np.sqrt(np.asarray(self.sigma_diag, dtype=float))

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out['candidates'] = list(self.candidates)
        out['sigma_diag'] = list(self.sigma_diag)
        return out


# ---------------------------------------------------------------------------- differentiator
def body_velocities(t_ns: np.ndarray, poses: np.ndarray, half_window_s: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Differentiate poses (N, 3) by local quadratic fits; return body twists (N, 3) and valid.

    Each pose's window holds the poses within +-half_window_s; at least 4 are needed (and one on
    each side) for a valid estimate. World velocities are rotated into the body frame with the
    fitted heading.
    """
    t_s = (np.asarray(t_ns, dtype=np.int64) - int(t_ns[0])) * 1e-9 if len(t_ns) else np.zeros(0)
    n = t_s.size
    out = np.zeros((n, 3))
    valid = np.zeros(n, dtype=bool)
    if n < 4:
        return out, valid
    lo = np.searchsorted(t_s, t_s - half_window_s, side='left')
    hi = np.searchsorted(t_s, t_s + half_window_s, side='right')
    width = int((hi - lo).max())
    offsets = np.arange(width)
    index = lo[:, None] + offsets[None, :]
    inside = index < hi[:, None]
    index = np.minimum(index, n - 1)
    tau = np.where(inside, t_s[index] - t_s[:, None], 0.0)
    weight = inside.astype(float)
    basis = np.stack([np.ones_like(tau), tau, tau * tau], axis=-1) * weight[..., None]
    normal = np.einsum('nwi,nwj->nij', basis, basis)
    left = (tau < 0) & inside
    right = (tau > 0) & inside
    valid = (inside.sum(axis=1) >= 4) & left.any(axis=1) & right.any(axis=1)
    normal[~valid] = np.eye(3)
    values = poses[index]  # (n, w, 3)
    rhs = np.einsum('nwi,nwc->nic', basis, values)
    coef = np.linalg.solve(normal, rhs)  # (n, 3 basis, 3 coords)
    vx_w, vy_w, omega = coef[:, 1, 0], coef[:, 1, 1], coef[:, 1, 2]
    yaw = coef[:, 0, 2]
    cos_y, sin_y = np.cos(yaw), np.sin(yaw)
    out[:, 0] = cos_y * vx_w + sin_y * vy_w
    out[:, 1] = -sin_y * vx_w + cos_y * vy_w
    out[:, 2] = omega
    return out, valid


def truth_velocities(drive: Drive, half_window_s: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (fresh ground-truth stamps, body twists (N, 3), valid) of one drive."""
    truth = drive.truth
    fresh = fresh_pose_mask(truth.x, truth.y, truth.yaw) & truth.valid
    t_ns = truth.t_ns[fresh]
    twist, valid = body_velocities(t_ns, truth.poses[fresh], half_window_s)
    return t_ns, twist, valid


# ---------------------------------------------------------------------------- sparse regression
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


# ---------------------------------------------------------------------------- model state
@dataclass(frozen=True)
class ModelState:
    """A structure with its values: base values and {extension: {param: value}}."""

    extensions: tuple[str, ...]
    base_values: dict[str, float]
    ext_values: dict[str, dict[str, float]]
    sparse_terms: tuple[str, ...] = ()
    found: tuple[str, ...] = ()

    def bind(self, base_name: str, geometry: Geometry) -> BoundModel | BoundAugmented:
        model = get_model(base_name)
        base = BoundModel(model, geometry, model.vector(self.base_values, geometry))
        if not self.extensions:
            return base
        return AugmentedModel(base_name, self.extensions).bind(base, self.ext_values)


def _bind_raw(base_name: str, geometry: Geometry, base_k: np.ndarray, extensions: tuple[str, ...],
              ext_k: Sequence[np.ndarray]) -> BoundModel | BoundAugmented:
    """Bind without validation (inside the optimizer, bounds already hold)."""
    base = BoundModel(get_model(base_name), geometry, np.asarray(base_k, dtype=float))
    if not extensions:
        return base
    return BoundAugmented(base, extensions, tuple(np.asarray(k, float) for k in ext_k))


@dataclass
class _Layout:
    """Which entries of the optimizer vector map to which parameters."""

    base_name: str
    geometry: Geometry
    extensions: tuple[str, ...]
    base_k: np.ndarray
    ext_k: list[np.ndarray]
    free: list[tuple[int, int]]  # (-1 for base | extension index, parameter index)

    def vector(self) -> np.ndarray:
        return np.array([self.base_k[j] if i < 0 else self.ext_k[i][j] for i, j in self.free])

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = [], []
        base_specs = get_model(self.base_name).params
        for i, j in self.free:
            spec = base_specs[j] if i < 0 else get_extension(self.extensions[i]).params[j]
            low, high = spec.optimizer_bounds()
            lo.append(low)
            hi.append(high)
        return np.array(lo), np.array(hi)

    def source(self, vector: np.ndarray) -> BoundModel | BoundAugmented:
        base_k = self.base_k.copy()
        ext_k = [k.copy() for k in self.ext_k]
        for value, (i, j) in zip(vector, self.free):
            if i < 0:
                base_k[j] = value
            else:
                ext_k[i][j] = value
        return _bind_raw(self.base_name, self.geometry, base_k, self.extensions, ext_k)

    def state(self, vector: np.ndarray, like: ModelState) -> ModelState:
        source = self.source(vector)
        base = source if isinstance(source, BoundModel) else source.base
        ext_values = {} if isinstance(source, BoundModel) else source.extension_values()
        return ModelState(self.extensions, base.values, ext_values, like.sparse_terms,
                          like.found)


def _layout(base_name: str, geometry: Geometry, state: ModelState, refit_base: bool,
            fixed: Sequence[str] = ()) -> _Layout:
    model = get_model(base_name)
    base_k = model.vector(state.base_values, geometry)
    ext_k = [get_extension(n).vector(state.ext_values.get(n, {})) for n in state.extensions]
    free = [(-1, j) for j in range(len(model.params))] if refit_base else []
    for i, name in enumerate(state.extensions):
        if name not in state.found:
            continue  # a structural part (the stamp convention): kept as it is
        ext = get_extension(name)
        names = ext.fitted
        if name == SPARSE:
            names = state.sparse_terms
        for j, pname in enumerate(ext.param_names):
            if (pname in names and f'{name}.{pname}' not in fixed
                    and (pname not in ext.scan or ext.refine)):
                free.append((i, j))
    return _Layout(base_name, geometry, state.extensions, base_k, ext_k, free)


def _fit(predictor: SegmentPredictor, base_name: str, geometry: Geometry, state: ModelState,
         options: DiagnosisOptions, keep: np.ndarray | None = None,
         refit_base: bool | None = None, fixed: Sequence[str] = ()) -> tuple[ModelState, float]:
    """Bounded least squares of the free parameters on the (kept) segments; (state, cost)."""
    refit = options.refit_base if refit_base is None else refit_base
    layout = _layout(base_name, geometry, state, refit, fixed)
    weight = options.whitening

    def residuals(vector: np.ndarray) -> np.ndarray:
        err = predictor.errors(layout.source(vector), keep) * weight
        return np.nan_to_num(err, nan=1e3, posinf=1e3, neginf=-1e3).ravel()

    x0 = layout.vector()
    if x0.size == 0:
        res = residuals(x0)
        return state, float(0.5 * res @ res)
    lo, hi = layout.bounds()
    x0 = np.clip(x0, lo, hi)
    sol = optimize.least_squares(residuals, x0, bounds=(lo, hi), x_scale='jac', method='trf',
                                 max_nfev=options.max_nfev * (x0.size + 1))
    return layout.state(sol.x, state), float(sol.cost)


def _loss(predictor: SegmentPredictor, source: Any, options: DiagnosisOptions,
          keep: np.ndarray | None = None) -> np.ndarray:
    err = predictor.errors(source, keep) * options.whitening
    return np.nan_to_num((err ** 2).sum(axis=1), nan=1e6, posinf=1e6)


# ---------------------------------------------------------------------------- trace
@dataclass(frozen=True)
class Trace:
    """Per-pose residuals of the model before diagnosis and the signals they are tested on.

    residual: (N, 3) ground truth - model body twist (v_x m/s, v_y m/s, omega rad/s);
    signals: {name: (N,)}; correlation: {(component, signal): Pearson r}; lag_s: the offset that
    best aligns the model's velocities with the ground truth's (positive: motion lags wheels).
    """

    residual: np.ndarray
    signals: dict[str, np.ndarray]
    correlation: dict[tuple[str, str], float]
    lag_s: float
    lag_curve: tuple[np.ndarray, np.ndarray]
    segment_errors: np.ndarray

    def top(self, count: int = 8) -> list[tuple[str, str, float]]:
        """Return the strongest (component, signal, r) correlations, strongest first."""
        items = sorted(((c, s, r) for (c, s), r in self.correlation.items()
                        if math.isfinite(r)), key=lambda item: -abs(item[2]))
        return items[:count]


COMPONENTS = ('v_x', 'v_y', 'omega')


def _model_velocities(source: Any, drive: Drive, t_ns: np.ndarray,
                      half_window_s: float, max_dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Model body twists at the stamps, through the same differentiator as the ground truth."""
    wheels = drive.wheels
    poses = rollout_stream(source, wheels.t_ns, wheels.omega_l, wheels.omega_r,
                           max_dt_s=max_dt_s)
    shift = int(getattr(source, 'output_offset_ns', 0))
    at = np.asarray(t_ns, dtype=np.int64) - shift
    ref = wheels.t_ns
    model_poses = np.stack([np.interp(at, ref, poses[:, i]) for i in range(3)], axis=-1)
    return body_velocities(t_ns, model_poses, half_window_s)


@dataclass(frozen=True)
class _PoseSamples:
    """Fresh ground-truth poses of all drives, with their velocities and signals."""

    drive: np.ndarray
    t_ns: np.ndarray
    truth: np.ndarray
    valid: np.ndarray
    signals: dict[str, np.ndarray]
    base_twist: np.ndarray


def _held(wheels, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    index = np.clip(np.searchsorted(wheels.t_ns, t_ns, side='right') - 1, 0, len(wheels) - 1)
    return wheels.omega_l[index], wheels.omega_r[index]


def _pose_samples(drives: Sequence[Drive], base: BoundModel,
                  options: DiagnosisOptions) -> _PoseSamples:
    parts = {key: [] for key in ('drive', 't', 'truth', 'valid', 'base')}
    signals: dict[str, list[np.ndarray]] = {}
    for index, drive in enumerate(drives):
        if drive.truth is None or len(drive.truth) < 4 or len(drive.wheels) < 2:
            continue
        t_ns, twist, valid = truth_velocities(drive, options.smoothing_s)
        wheels = drive.wheels
        wl, wr = _held(wheels, t_ns)
        t_w = wheels.t_s
        dwl = np.interp(t_ns, wheels.t_ns, np.gradient(wheels.omega_l, t_w)
                        if len(wheels) > 2 else np.zeros(len(wheels)))
        dwr = np.interp(t_ns, wheels.t_ns, np.gradient(wheels.omega_r, t_w)
                        if len(wheels) > 2 else np.zeros(len(wheels)))
        model_twist = base.twist(wl, wr)
        v, w = model_twist[:, 0], model_twist[:, 2]
        big = np.maximum(np.abs(wl), np.abs(wr))
        small = np.minimum(np.abs(wl), np.abs(wr))
        ratio = np.where((wl * wr > 0) & (big > 0), small / np.where(big > 0, big, 1), -1.0)
        poses = drive.truth.interpolate(t_ns)
        named = {
            'omega_l': wl, 'omega_r': wr, 'wheel_sum': wl + wr, 'wheel_diff': wr - wl,
            'wheel_ratio': ratio, 'd_omega_l': dwl, 'd_omega_r': dwr,
            'd_wheel_sum': dwl + dwr, 'd_wheel_diff': dwr - dwl,
            'body_speed': v, 'yaw_rate': w,
            'curvature': np.clip(w / np.where(np.abs(v) > 0.05, v, np.nan), -20, 20),
            'v_omega': v * w, 'v_abs_v': v * np.abs(v), 'direction': np.sign(v),
            'time_in_drive': (t_ns - wheels.t_ns[0]) * 1e-9,
            'x': poses[:, 0], 'y': poses[:, 1],
        }
        imu = drive.imu
        if imu is not None and len(imu.t_ns) > 1:
            named['imu_yaw_rate'] = np.interp(t_ns, imu.t_ns, imu.yaw_rate)
        for key, value in named.items():
            signals.setdefault(key, []).append(np.asarray(value, dtype=float))
        parts['drive'].append(np.full(t_ns.size, index))
        parts['t'].append(t_ns)
        parts['truth'].append(twist)
        parts['valid'].append(valid)
        parts['base'].append(model_twist)
    if not parts['t']:
        raise DataError('no drive has at least 4 ground-truth poses: nothing to diagnose')
    count = sum(p.size for p in parts['t'])
    merged = {}
    for key, values in signals.items():
        merged[key] = np.concatenate(values) if sum(v.size for v in values) == count else None
    merged = {k: v for k, v in merged.items() if v is not None}
    return _PoseSamples(np.concatenate(parts['drive']), np.concatenate(parts['t']),
                        np.concatenate(parts['truth']), np.concatenate(parts['valid']),
                        merged, np.concatenate(parts['base']))


def pose_residuals(drives: Sequence[Drive], samples: _PoseSamples, source: Any,
                   options: DiagnosisOptions) -> tuple[np.ndarray, np.ndarray]:
    """Return (residual (N, 3) = truth - model body twist, valid (N,)) at the fresh poses."""
    residual = np.zeros(samples.truth.shape)
    valid = samples.valid.copy()
    for index in np.unique(samples.drive):
        rows = samples.drive == index
        model, ok = _model_velocities(source, drives[index], samples.t_ns[rows],
                                      options.smoothing_s, options.max_dt_s)
        residual[rows] = samples.truth[rows] - model
        valid[rows] &= ok
    return residual, valid


def _correlations(residual: np.ndarray, valid: np.ndarray,
                  signals: Mapping[str, np.ndarray]) -> dict[tuple[str, str], float]:
    out = {}
    for c, component in enumerate(COMPONENTS):
        target = residual[valid, c]
        for name, signal in signals.items():
            values = signal[valid]
            ok = np.isfinite(values) & np.isfinite(target)
            if ok.sum() < 10 or np.std(values[ok]) == 0 or np.std(target[ok]) == 0:
                out[(component, name)] = math.nan
                continue
            out[(component, name)] = float(np.corrcoef(values[ok], target[ok])[0, 1])
    return out


def _lag_scan(drives: Sequence[Drive], samples: _PoseSamples, state: ModelState,
              base_name: str, geometry: Geometry, options: DiagnosisOptions
              ) -> tuple[float, tuple[np.ndarray, np.ndarray]]:
    """Refit the velocity residual over offsets; return the best offset and the curve."""
    step = 0.01
    lags = np.arange(-options.lag_range_s, options.lag_range_s + step / 2, step)
    base = state.bind(base_name, geometry)
    base = base if isinstance(base, BoundModel) else base.base
    cost = np.zeros(lags.size)
    scale = np.array([1.0, 1.0, geometry.track_width / 2])
    for i, lag in enumerate(lags):
        source = AugmentedModel(base_name, ['time_offset']).bind(
            base, {'time_offset': {'offset_s': float(lag)}})
        residual, valid = pose_residuals(drives, samples, source, options)
        cost[i] = float(np.mean(((residual[valid] * scale) ** 2).sum(axis=1)))
    best = int(np.argmin(cost))
    return float(lags[best]), (lags, cost)


# ---------------------------------------------------------------------------- results
@dataclass(frozen=True)
class CandidateScore:
    """One candidate in one round of the forward selection."""

    round_no: int
    name: str
    relative_gain: float
    p_value: float
    accepted: bool
    values: dict[str, float]
    terms: tuple[str, ...] = ()
    seconds: float = 0.0  # fitting time, summed over its tasks (which may run in parallel)
    note: str = ''


@dataclass(frozen=True)
class ModelStep:
    """One model of the before/after table, with its held-out errors."""

    label: str
    state: ModelState
    eps_t: np.ndarray
    eps_theta_deg: np.ndarray
    stats_t: ErrorStats
    stats_theta: ErrorStats


@dataclass(frozen=True)
class DiagnosisResult:
    """What :func:`diagnose` found (the report and the parameters file are made from it)."""

    base_model: str
    geometry: Geometry
    options: DiagnosisOptions
    trace: Trace
    candidates: tuple[CandidateScore, ...]
    steps: tuple[ModelStep, ...]
    final: ModelState
    residual_after: np.ndarray
    residual_valid: np.ndarray
    residual_after_valid: np.ndarray
    holdout: str = 'given'
    warnings: tuple[str, ...] = ()
    provenance: dict[str, Any] = field(default_factory=dict)

    @property
    def extensions(self) -> tuple[str, ...]:
        """Return the extensions the diagnosis found (the stamp convention is not one)."""
        return self.final.found

    @property
    def convention_s(self) -> float:
        return float(self.provenance.get('stamp_convention_s', 0.0))

    def bound(self) -> BoundModel | BoundAugmented:
        """Return the final (augmented) model, ready for the integrator."""
        return self.final.bind(self.base_model, self.geometry)

    def summary_lines(self) -> list[str]:
        """Return the findings and the before/after table as text lines (for stdout)."""
        lines = [f'diagnosis of {self.base_model} ({self.holdout})']
        lag = self.trace.lag_s
        lines.append(f'  wheel -> ground-truth lag (velocity refit): {lag * 1e3:+.0f} ms, '
                     f'beyond the stamp convention ({self.convention_s * 1e3:+.0f} ms: speeds '
                     'held from their stamp describe the middle of the interval)')
        lines.append('  strongest residual correlations: ' + ', '.join(
            f'{c}~{s} r={r:+.2f}' for c, s, r in self.trace.top(4)))
        if not self.final.found:
            lines.append('  no extension added: no candidate passed the parsimony rule '
                         f'(held-out gain > {self.options.min_relative_gain:.0%} and p < '
                         f'{self.options.significance:g})')
        for name in self.final.found:
            values = self.final.ext_values.get(name, {})
            ext = get_extension(name)
            if name == SPARSE:
                shown = {t: values[t] for t in self.final.sparse_terms}
            else:
                shown = {p: values[p] for p in ext.fitted + ext.scan}
            text = ', '.join(f'{k} = {v:.4g} {_unit(ext, k)}' for k, v in shown.items())
            lines.append(f'  added {name} ({ext.title}): {text}')
            notes = [c.note for c in self.candidates if c.accepted and c.name == name and c.note]
            lines += [f'    note: {note}' for note in notes]
        lines.append('  candidates (round, name, held-out gain, p, accepted):')
        for cand in self.candidates:
            terms = f' terms {list(cand.terms)}' if cand.terms else ''
            lines.append(f'    {cand.round_no} {cand.name:<20} {cand.relative_gain:+7.1%} '
                         f'p={cand.p_value:.2g} {"yes" if cand.accepted else "no"}{terms}')
        lines.append('  held-out errors: model | eps_t m/m median [q25, q75] p90 | '
                     'eps_theta deg/m median [q25, q75] p90 | segments')
        for step in self.steps:
            t, th = step.stats_t, step.stats_theta
            lines.append(f'    {step.label:<34} {t.median:.4f} [{t.q25:.4f}, {t.q75:.4f}] '
                         f'{t.p90:.4f} | {th.median:.3f} [{th.q25:.3f}, {th.q75:.3f}] '
                         f'{th.p90:.3f} | {t.count}')
        lines += [f'  warning: {w}' for w in self.warnings]
        return lines

    def table_rows(self) -> list[list[str]]:
        """Return the before/after table rows (model, eps_t median/q25/q75/p90, eps_theta ...)."""
        rows = []
        for step in self.steps:
            t, th = step.stats_t, step.stats_theta
            rows.append([step.label] + [f'{v:.4f}' for v in (t.median, t.q25, t.q75, t.p90)]
                        + [f'{v:.3f}' for v in (th.median, th.q25, th.q75, th.p90)])
        return rows

    def to_parameters(self, base_flat: Mapping[str, Any]) -> dict[str, Any]:
        """Return complete flat parameters for ``config.write_params_file``.

        ``base_flat`` is the calibrated parameters file (flat, its provenance dropped: give
        ``self.provenance`` to write_params_file); the result keeps it and sets
        model = augmented, augmented.base, augmented.extensions and every extension value, and
        the base model's parameters as fitted jointly with the extensions. With no extension the
        base model is kept (model = base).
        """
        flat = {k: v for k, v in base_flat.items() if not k.startswith('provenance.')}
        flat['wheel_radius'] = float(self.geometry.wheel_radius)
        flat['track_width'] = float(self.geometry.track_width)
        if not self.final.found:
            flat['model'] = self.base_model
            return flat
        for name, value in self.final.base_values.items():
            flat[f'models.{self.base_model}.{name}'] = float(value)
        flat['model'] = AUGMENTED_NAME
        flat['augmented.base'] = self.base_model
        flat['augmented.extensions'] = ', '.join(self.final.extensions)
        for name in self.final.extensions:
            for param, value in self.final.ext_values[name].items():
                flat[f'augmented.{name}.{param}'] = float(value)
        return flat


def _unit(ext, param: str) -> str:
    for spec in ext.params:
        if spec.name == param:
            return spec.unit
    return ''


# ---------------------------------------------------------------------------- selection
def _fold_labels(drives: Sequence[Drive], segments: SegmentSet, folds: int) -> np.ndarray:
    """Assign each segment to a fold: by calib_step, by drive, or interleaved time blocks."""
    count = len(segments)
    if count == 0:
        return np.zeros(0, dtype=int)
    steps = [d.meta.get('calib_step') for d in drives]
    if all(s is not None for s in steps):
        keys = np.array([int(steps[d]) for d in segments.drive])
        _, groups = np.unique(keys, return_inverse=True)
        return groups % folds
    if len(drives) >= 2 * folds:
        return segments.drive % folds
    labels = np.zeros(count, dtype=int)
    blocks = 3 * folds
    for d in np.unique(segments.drive):
        rows = np.nonzero(segments.drive == d)[0]
        order = rows[np.argsort(segments.t_a_ns[rows], kind='stable')]
        block = (np.arange(order.size) * blocks) // max(order.size, 1)
        labels[order] = block % folds
    return labels


def _p_greater(diff: np.ndarray, untestable: float) -> float:
    """Return the one-sided Wilcoxon p-value that ``diff`` is above 0.

    ``untestable`` is returned when fewer than 5 differences are non-zero or the test fails.
    """
    if np.count_nonzero(diff) < 5:
        return untestable
    try:
        return float(stats.wilcoxon(diff, alternative='greater').pvalue)
    except ValueError:
        return untestable


def _significance(null: np.ndarray, cand: np.ndarray) -> tuple[float, float]:
    total = float(null.sum())
    gain = 1.0 - float(cand.sum()) / total if total > 0 else 0.0
    return gain, _p_greater(null - cand, untestable=1.0)


class _Diagnoser:
    """The candidate fitting and selection over one training set."""

    def __init__(self, drives: Sequence[Drive], segments: SegmentSet, base_name: str,
                 geometry: Geometry, options: DiagnosisOptions, samples: _PoseSamples,
                 lag_s: float, convention_s: float, jobs: int = 1,
                 progress: Progress | None = None) -> None:
        self.convention_s = convention_s
        self.jobs = jobs
        self.progress = progress
        self.period_s = _wheel_period_s(drives)
        self.drives = drives
        self.predictor = SegmentPredictor(drives, segments, options.max_dt_s)
        self.base_name = base_name
        self.geometry = geometry
        self.options = options
        self.samples = samples
        self.lag_s = lag_s
        self.labels = _fold_labels(drives, segments, options.folds)
        durations = [d.duration_s() for d in drives]
        self.max_time_s = max(durations) if durations else 0.0

    def with_extension(self, state: ModelState, name: str,
                       keep: np.ndarray | None = None,
                       threshold: float | None = None) -> ModelState:
        """Return the state plus the extension at its start values (and sparse terms).

        ``threshold``: the sparse fallback's STLSQ threshold (default: the smallest of the
        options').
        """
        ext = get_extension(name)
        values = dict(state.ext_values)
        start = ext.defaults()
        terms = state.sparse_terms
        if name == 'time_offset':
            start['offset_s'] = float(np.clip(self.lag_s + self.convention_s, -0.45, 0.45))
        elif name == 'first_order_lag':
            start['tau_s'] = float(np.clip(abs(self.lag_s), 0.03, 1.5))
        elif name == SPARSE:
            start, terms = self.sparse_start(state, keep, threshold)
        values[name] = start
        structure = state.extensions if name in state.extensions else state.extensions + (name,)
        return ModelState(ordered(structure), dict(state.base_values), values, terms,
                          state.found + (name,))

    def sparse_start(self, state: ModelState, keep: np.ndarray | None,
                     threshold: float | None = None) -> tuple[dict[str, float], tuple[str, ...]]:
        if threshold is None:
            threshold = min(self.options.sparse_thresholds)
        source = state.bind(self.base_name, self.geometry)
        residual, valid = pose_residuals(self.drives, self.samples, source, self.options)
        if keep is not None:
            drives_kept = np.unique(self.predictor.segments.drive[keep])
            valid &= np.isin(self.samples.drive, drives_kept)
        features = sparse_features(self.samples.base_twist)[valid]
        values = {}
        terms = []
        for c, out in enumerate(('vx', 'vy', 'wz')):
            coef = stlsq(features, residual[valid, c], threshold)
            for (feat, _), value in zip(SPARSE_FEATURES, coef):
                if value != 0.0:
                    name = f'{out}_{feat}'
                    values[name] = float(np.clip(value, -9.9, 9.9))
                    terms.append(name)
        return values, tuple(terms)

    def fit(self, state: ModelState, keep: np.ndarray | None = None,
            scan: str | None = None) -> ModelState:
        """Fit a structure on the (kept) segments.

        The step-like parameters of the extension ``scan`` are grid-searched first (those of
        the other extensions keep the values they have).
        """
        if scan is not None:
            for param in get_extension(scan).scan:
                state = self._scan(state, scan, param, keep)
        fixed = [f'{n}.{p}' for n in state.extensions for p in get_extension(n).scan
                 if not get_extension(n).refine]
        fitted, _ = _fit(self.predictor, self.base_name, self.geometry, state, self.options,
                         keep, fixed=fixed)
        return fitted

    def _scan_cost(self, state: ModelState, name: str, param: str, value: float,
                   keep: np.ndarray | None) -> tuple[ModelState, float]:
        values = {k: dict(v) for k, v in state.ext_values.items()}
        values[name][param] = float(value)
        trial = ModelState(state.extensions, state.base_values, values, state.sparse_terms,
                           state.found)
        return _fit(self.predictor, self.base_name, self.geometry, trial,
                    replace_options(self.options, max_nfev=10), keep, refit_base=False,
                    fixed=(f'{name}.{param}',))

    def _scan(self, state: ModelState, name: str, param: str,
              keep: np.ndarray | None) -> ModelState:
        """Search a coarse grid over the drive duration, then a fine grid around the best."""
        count = self.options.scan_points
        grid = np.linspace(0.05, 0.95, count) * self.max_time_s
        best = min((self._scan_cost(state, name, param, v, keep) + (v,) for v in grid),
                   key=lambda item: item[1])
        step = grid[1] - grid[0] if count > 1 else self.max_time_s
        fine = best[2] + np.linspace(-step, step, count)
        fine = fine[(fine > 0) & (fine < self.max_time_s)]
        candidates = [best] + [self._scan_cost(state, name, param, v, keep) + (v,)
                               for v in fine]
        return min(candidates, key=lambda item: item[1])[0]

    def prepare(self, name: str | None):
        """Return a function (state, keep) -> fitted state for the CV of one candidate.

        ``name``: an extension, a sparse variant (``sparse_correction@THRESHOLD``), or None for
        the current model alone.
        """
        ext, threshold = _variant(name)

        def run(state: ModelState, keep: np.ndarray | None) -> ModelState:
            if ext is not None:
                state = self.with_extension(state, ext, keep, threshold)
            return self.fit(state, keep, scan=ext)
        return run

    def _task(self, task: tuple[ModelState, str | None, int | None]) -> tuple[Any, float]:
        """Run one unit of the selection; return (its value, seconds).

        (state, name, fold): the state (plus the candidate ``name``, None for the current model
        alone) fitted without ``fold`` and scored on it, giving that fold's per-segment held-out
        losses (None when the fold or the rest is empty); fold None: the candidate fitted on all
        training segments, giving its state.
        """
        tic = time.perf_counter()
        state, name, fold = task
        if fold is None:
            value: Any = self.prepare(name)(state, None)
        else:
            test = np.nonzero(self.labels == fold)[0]
            train = np.nonzero(self.labels != fold)[0]
            value = None
            if test.size and train.size:
                fitted = self.prepare(name)(state, train)
                value = _loss(self.predictor, fitted.bind(self.base_name, self.geometry),
                              self.options, test)
        return value, time.perf_counter() - tic

    def _held_out(self, values: Mapping[int, Any]) -> np.ndarray:
        """Assemble the per-segment held-out losses from the fold results."""
        losses = np.zeros(len(self.predictor))
        for fold, value in values.items():
            if value is not None:
                losses[self.labels == fold] = value
        return losses

    def _run_round(self, state: ModelState, names: Sequence[str], with_null: bool,
                   round_index: int) -> dict[tuple[str | None, int | None], tuple[Any, float]]:
        """Run every task of a round (on ``jobs`` cores); results keyed by (name, fold)."""
        folds: tuple[int | None, ...] = tuple(range(self.options.folds))
        keys = [(None, fold) for fold in folds] if with_null else []
        # The grid-searched candidates are the longest: started first, they finish with the rest.
        by_cost = sorted(names, key=lambda n: not get_extension(_variant(n)[0]).scan)
        keys += [(name, fold) for name in by_cost for fold in folds + (None,)]
        progress = self.progress
        on_done = (None if progress is None
                   else lambda done, total: progress(round_index, done, total))
        values = fork_map(self._task, [(state, name, fold) for name, fold in keys], self.jobs,
                          on_done)
        return dict(zip(keys, values))

    def select(self, start: ModelState) -> tuple[ModelState, list[CandidateScore],
                                                 list[ModelState]]:
        options = self.options
        current = start
        scores: list[CandidateScore] = []
        accepted_states: list[ModelState] = []
        folds = range(options.folds)
        for round_index in range(1, options.max_extensions + 1):
            pool = [n for n in options.candidates if n not in current.found]
            named = [n for n in pool if n != SPARSE]
            round_scores = []
            notes: dict[str, str] = {}
            null = None
            sparse = [f'{SPARSE}@{t:g}' for t in sorted(set(options.sparse_thresholds))]
            for group in (named, sparse if SPARSE in pool else []):
                if not group:
                    continue
                results = self._run_round(current, group, null is None, round_index)
                if null is None:
                    null = self._held_out({f: results[None, f][0] for f in folds})
                outcomes = {}
                for name in group:
                    losses = self._held_out({f: results[name, f][0] for f in folds})
                    full, seconds = results[name, None]
                    seconds += sum(results[name, f][1] for f in folds)
                    outcomes[name] = (losses, full, seconds)
                if group is sparse:
                    outcomes, notes[SPARSE] = _sparsest(outcomes)
                for name, (losses, full, seconds) in outcomes.items():
                    gain, p_value = _significance(null, losses)
                    passes = gain > options.min_relative_gain and p_value < options.significance
                    round_scores.append((passes, gain, name, losses, full, p_value, seconds))
                    LOG.info('round %d %s: held-out gain %.3f p %.3g', round_index, name, gain,
                             p_value)
                if any(item[0] for item in round_scores):
                    break
            best, tied = _pick(round_scores, options, self.period_s)
            for passes, gain, name, _, full, p_value, seconds in round_scores:
                terms = full.sparse_terms if name == SPARSE else ()
                values = dict(full.ext_values.get(name, {}))
                if name == SPARSE:
                    values = {t: values[t] for t in terms}
                chosen = best is not None and name == best[2]
                note = (f'indistinguishable from {", ".join(tied)} on this data; the simpler '
                        'explanation is kept' if chosen and tied else '')
                note = '; '.join(part for part in (notes.get(name, ''), note) if part)
                scores.append(CandidateScore(round_index, name, gain, p_value, chosen, values,
                                             terms, seconds, note))
            if best is None:
                break
            current = best[4]
            accepted_states.append(current)
        return current, scores, accepted_states


def _variant(name: str | None) -> tuple[str | None, float | None]:
    """Split a candidate name into (extension, sparse threshold or None)."""
    if name is None or '@' not in name:
        return name, None
    ext, _, threshold = name.partition('@')
    return ext, float(threshold)


def _sparsest(outcomes: Mapping[str, tuple[np.ndarray, ModelState, float]]
              ) -> tuple[dict[str, tuple[np.ndarray, ModelState, float]], str]:
    """Keep the sparse variant with the fewest terms among those as good as the best.

    ``outcomes``: variant name -> (per-segment held-out losses, fitted state, seconds). A variant
    is as good as the one with the lowest total held-out loss unless a one-sided Wilcoxon test
    says its per-segment losses are higher (p < TIE_SIGNIFICANCE). Returns {SPARSE: the kept
    outcome (its seconds: all variants')} and a note naming the threshold kept.
    """
    best = min(outcomes, key=lambda n: outcomes[n][0].sum())
    as_good = []
    for name, (losses, full, _) in outcomes.items():
        p_value = (1.0 if name == best
                   else _p_greater(losses - outcomes[best][0], untestable=1.0))
        if p_value >= TIE_SIGNIFICANCE:
            as_good.append((len(full.sparse_terms), -_variant(name)[1], name))
    kept = min(as_good)[2]
    losses, full, _ = outcomes[kept]
    seconds = sum(item[2] for item in outcomes.values())
    counts = ', '.join(f'{_variant(n)[1]:g}: {len(o[1].sparse_terms)}'
                       for n, o in outcomes.items())
    note = (f'STLSQ threshold {_variant(kept)[1]:g} kept (terms by threshold: {counts}); the '
            'fewest terms whose held-out loss is not significantly above the best')
    return {SPARSE: (losses, full, seconds)}, note


def _complexity(name: str, item: tuple) -> tuple[int, int]:
    """Return (free parameters, 1 if it carries state): the simpler explanation sorts first."""
    ext = get_extension(name)
    count = len(item[4].sparse_terms) if name == SPARSE else len(ext.fitted) + len(ext.scan)
    return count, int(ext.stage == 'dynamics')


def _pick(round_scores: list[tuple], options: DiagnosisOptions, period_s: float
          ) -> tuple[tuple | None, list[str]]:
    """Return the accepted candidate of a round and the passing ones it could not be told from.

    The best held-out gain wins, unless a simpler passing candidate is not significantly worse
    (one-sided Wilcoxon on the per-segment held-out losses, p >= TIE_SIGNIFICANCE): a small
    time offset and a short first-order lag, for instance, fit a drive almost equally well.
    A first-order lag no longer than one wheel sample period cannot be told from a delay when
    the speeds are held between stamps: the (stateless) time offset is kept then.
    """
    winners = [item for item in round_scores if item[0]]
    if not winners:
        return None, []
    best = max(winners, key=lambda item: item[1])
    offset = [item for item in winners if item[2] == 'time_offset']
    if (best[2] == 'first_order_lag' and offset
            and best[4].ext_values['first_order_lag']['tau_s'] <= period_s):
        return offset[0], ['first_order_lag']
    tied = []
    for item in winners:
        if item is best:
            continue
        if _p_greater(item[3] - best[3], untestable=0.0) >= TIE_SIGNIFICANCE:
            tied.append(item)
    if not tied:
        return best, []
    group = [best] + tied
    chosen = min(group, key=lambda item: (_complexity(item[2], item), -item[1]))
    return chosen, [item[2] for item in group if item is not chosen]


def replace_options(options: DiagnosisOptions, **changes: Any) -> DiagnosisOptions:
    """Return a copy of the options with some fields changed."""
    values = {**{k: getattr(options, k) for k in options.__dataclass_fields__}, **changes}
    return DiagnosisOptions(**values)


def _evaluate(predictor: SegmentPredictor, label: str, state: ModelState, base_name: str,
              geometry: Geometry, options: DiagnosisOptions) -> ModelStep:
    errors = predictor.errors(state.bind(base_name, geometry))
    eps_t, eps_th = relative_errors(errors, predictor.segments.path_m, options.min_eval_path_m)
    return ModelStep(label, state, eps_t, eps_th, ErrorStats.of(eps_t), ErrorStats.of(eps_th))


def _wheel_period_s(drives: Sequence[Drive]) -> float:
    """Return the median wheel sample period (s) of the drives, 0 without samples."""
    steps = [np.diff(d.wheels.t_ns) for d in drives if len(d.wheels) > 1]
    steps = np.concatenate(steps) if steps else np.zeros(0)
    steps = steps[steps > 0]
    return float(np.median(steps)) * 1e-9 if steps.size else 0.0


def _stamp_convention(drives: Sequence[Drive], options: DiagnosisOptions) -> float:
    """Return -dt/2 (s) for options.stamp_convention 'mid' (median wheel period), else 0."""
    if options.stamp_convention != 'mid':
        return 0.0
    return -0.5 * _wheel_period_s(drives)


def diagnose(train: Sequence[Drive], evaluate: Sequence[Drive] | None, geometry: Geometry,
             base_values_by_model: Mapping[str, Mapping[str, float]], base_model_name: str,
             options: DiagnosisOptions | None = None, jobs: int = 1,
             progress: Progress | None = None) -> DiagnosisResult:
    """Run the diagnosis recipe of the module docstring and return its result.

    ``jobs``: how many processes fit the candidates (the result does not depend on it);
    ``progress(round, done, total)`` is called as each fit of a selection round finishes.
    """
    options = options or DiagnosisOptions()
    model = get_model(base_model_name)
    given = dict(base_values_by_model.get(base_model_name, {}))
    model.vector(given, geometry)
    train, evaluate, holdout = resolve_holdout(train, evaluate, options.holdout_every,
                                               options.holdout_mode, options.holdout_block_s,
                                               options.holdout_key)
    tic = time.perf_counter()
    train_seg = usable_segments(train, options.train_segments(), 'training', 6, 'a diagnosis')
    eval_seg = usable_segments(evaluate, options.eval_segments(), 'evaluation', 6,
                               'a diagnosis')
    given_state = ModelState((), given, {})
    convention_s = _stamp_convention(train, options)
    predictor = SegmentPredictor(train, train_seg, options.max_dt_s)
    refit, _ = _fit(predictor, base_model_name, geometry, given_state, options)
    trimmed = 0
    if options.trim:
        # Outlier segments (e.g. ground-truth glitches, C15) are dropped once, as calibrate does.
        kept = trim_mask(predictor.errors(refit.bind(base_model_name, geometry)),
                         options.whitening)
        trimmed = int((~kept).sum())
        if trimmed:
            train_seg = train_seg.subset(kept)
            predictor = SegmentPredictor(train, train_seg, options.max_dt_s)
            refit, _ = _fit(predictor, base_model_name, geometry, refit, options)
    null = refit
    if convention_s != 0.0:
        null = ModelState(('time_offset',), dict(refit.base_values),
                          {'time_offset': {'offset_s': convention_s}})
        null, _ = _fit(predictor, base_model_name, geometry, null, options)
    base_bound = refit.bind(base_model_name, geometry)
    samples = _pose_samples(train, base_bound, options)
    residual, valid = pose_residuals(train, samples, null.bind(base_model_name, geometry),
                                     options)
    lag_s, curve = _lag_scan(train, samples, refit, base_model_name, geometry, options)
    lag_s -= convention_s
    trace = Trace(residual, samples.signals, _correlations(residual, valid, samples.signals),
                  lag_s, curve, predictor.errors(null.bind(base_model_name, geometry)))
    diagnoser = _Diagnoser(train, train_seg, base_model_name, geometry, options, samples, lag_s,
                           convention_s, jobs, progress)
    final, scores, accepted = diagnoser.select(null)
    eval_predictor = SegmentPredictor(evaluate, eval_seg, options.max_dt_s)
    steps = [_evaluate(eval_predictor, f'{base_model_name} (given)', given_state,
                       base_model_name, geometry, options),
             _evaluate(eval_predictor, f'{base_model_name} (refitted)', refit, base_model_name,
                       geometry, options)]
    if convention_s != 0.0:
        steps.append(_evaluate(eval_predictor, f'+ stamp convention {convention_s * 1e3:+.0f} ms',
                               null, base_model_name, geometry, options))
    for state in accepted:
        label = '+ ' + ' + '.join(state.found)
        steps.append(_evaluate(eval_predictor, label, state, base_model_name, geometry,
                               options))
    after, after_valid = pose_residuals(train, samples, final.bind(base_model_name, geometry),
                                        options)
    warnings = []
    if accepted and steps[-1].stats_t.median > steps[1].stats_t.median * 1.05:
        warnings.append('the augmented model is worse than the refitted base model on the '
                        'evaluation drives (median eps_t); the effect may not transfer')
    provenance = {
        'tool': f'skidkin_ros {__version__}', 'base_model': base_model_name,
        'extensions': list(final.found), 'model_extensions': list(final.extensions),
        'stamp_convention_s': convention_s, 'train_drives': len(train),
        'evaluate_drives': len(evaluate), 'train_segments': len(train_seg),
        'train_segments_trimmed': trimmed,
        'evaluate_segments': len(eval_seg), 'holdout': holdout,
        'seconds': round(time.perf_counter() - tic, 2), 'options': options.as_dict(),
    }
    return DiagnosisResult(base_model_name, geometry, options, trace, tuple(scores),
                           tuple(steps), final, after, valid, after_valid, holdout,
                           tuple(warnings), provenance)
