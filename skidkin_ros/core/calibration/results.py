"""The calibration's options and result: what shapes a calibration, what it found, what it writes.

:class:`CalibrationOptions` (saved with the results as provenance), :class:`CalibrationResult`
(the report and the parameters file are made from it) and :func:`result_to_parameters` (the flat
parameters a result writes). The recipe that fills them is
:mod:`skidkin_ros.core.calibration.pipeline`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
import math
from typing import Any, Mapping

import numpy as np

from skidkin_ros.core.calibration.evaluation import ModelEvaluation, WindowEnd
from skidkin_ros.core.calibration.fitting import FitOptions, FitResult
from skidkin_ros.core.calibration.gyro_fit import gyro_parameters, GyroFit
from skidkin_ros.core.calibration.noise_fit import NoiseFit
from skidkin_ros.core.calibration.segments import HorizonOptions, SegmentOptions, SegmentSet
from skidkin_ros.core.calibration.selection import Likelihood
from skidkin_ros.core.calibration.weighting import WEIGHTINGS
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.core.kinematics.models import get_model, MODEL_NAMES
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.noise import NOISE_SPECS
from skidkin_ros.errors import FitError, ParameterError

__all__ = ['CalibrationOptions', 'CalibrationResult', 'result_to_parameters', 'INTERVAL_SEARCHES',
           'SELECTIONS', 'TRAIN_SEGMENTS']

SELECTIONS = ('likelihood', 'paper')
INTERVAL_SEARCHES = ('fits', 'full')
TRAIN_SEGMENTS = ('rotation', 'paper', 'time')


@dataclass(frozen=True)
class CalibrationOptions(HorizonOptions):
    """Everything that shapes a calibration (saved with the results as provenance)."""

    loss: str = 'linear'
    f_scale: float = 1.0
    trim: bool = True
    n_starts: int = 8
    seed: int = 0
    models: tuple[str, ...] = MODEL_NAMES
    holdout_every: int = 3
    holdout_mode: str = 'auto'
    holdout_block_s: float = 60.0
    holdout_key: str | None = None
    noise_horizon_factors: tuple[float, ...] = (0.25, 0.5, 1.0, 2.0)
    noise_constant: bool = True
    noise_time: bool = True
    parameter_covariance: bool = True
    weighting: str = 'iterated'
    selection: str = 'likelihood'
    window_s: float = 2.0
    segments: str = 'rotation'
    jobs: int = 0   # models calibrated in parallel; 0: every usable CPU (no effect on results)

    def __post_init__(self) -> None:
        if self.segments not in TRAIN_SEGMENTS:
            raise ParameterError(f'segments must be one of {TRAIN_SEGMENTS}, '
                                 f'got {self.segments!r}')
        if self.weighting not in WEIGHTINGS:
            raise ParameterError(f'weighting must be one of {WEIGHTINGS}, got {self.weighting!r}')
        if self.selection not in SELECTIONS:
            raise ParameterError(f'selection must be one of {SELECTIONS}, '
                                 f'got {self.selection!r}')
        if not (math.isfinite(self.window_s) and self.window_s > 0):
            raise ParameterError(f'window_s must be a duration > 0 s, got {self.window_s!r}')
        for name in self.models:
            get_model(name)
        if not self.models:
            raise ParameterError('models must name at least one model')
        for name in ('h_t', 'h_e'):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ParameterError(f'{name} must be a distance > 0 m, got {value!r}')
        self.fit_options()

    def train_segments(self) -> SegmentOptions:
        """Training segments as ``segments`` says (the pipeline's docstring, step 1)."""
        base = super().train_segments()
        if self.segments == 'paper':
            return replace(base, horizon_rad=None)
        if self.segments == 'time':
            return replace(base, horizon_s=self.window_s, horizon_rad=None)
        return base

    def fit_options(self) -> FitOptions:
        return FitOptions(sigma_diag=tuple(self.sigma_diag), loss=self.loss,
                          f_scale=self.f_scale, trim=self.trim, n_starts=self.n_starts,
                          seed=self.seed)

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out['models'] = list(self.models)
        out['sigma_diag'] = list(self.sigma_diag)
        out['noise_horizon_factors'] = list(self.noise_horizon_factors)
        return out

    def noise_horizons(self) -> dict[float, SegmentOptions]:
        """Return the segment options of every noise-fit horizon but h_e itself."""
        base = self.eval_segments()
        return {self.h_e * f: replace(base, horizon_m=self.h_e * f)
                for f in self.noise_horizon_factors if f > 0 and f != 1.0}


@dataclass(frozen=True)
class CalibrationResult:
    """What :func:`calibrate` found (the report and the parameters file are made from it)."""

    geometry: Geometry
    options: CalibrationOptions
    fits: dict[str, FitResult]
    evaluation: dict[str, ModelEvaluation]
    noise: dict[str, NoiseFit]
    best: str
    scores: dict[str, float]
    warnings: tuple[str, ...]
    train_segments: SegmentSet = field(repr=False)
    eval_segments: SegmentSet = field(repr=False)
    holdout: str = 'given'
    provenance: dict[str, Any] = field(default_factory=dict)
    likelihood: dict[str, Likelihood] = field(default_factory=dict)
    window_end: dict[str, WindowEnd] = field(default_factory=dict)
    selection_rule: str = 'paper'
    # Held-out median (eps_t m/m, eps_theta deg/m) of the best model under each convention tried.
    interval_errors: dict[str, tuple[float, float]] = field(default_factory=dict)
    gyro: GyroFit | None = None
    # The evaluation drives' ground truth, indexed as eval_segments.drive (the report draws the
    # true path of a segment beside each model's).
    eval_truth: tuple[PoseTrack | None, ...] = field(default=(), repr=False)
    # The written model fitted the plain way (one segment per training window, unit weights, no
    # trimming), scored on the same held-out window ends: what a user would fit instead.
    plain_window_end: WindowEnd | None = None
    plain_values: dict[str, float] = field(default_factory=dict)

    @property
    def counts(self) -> dict[str, Any]:
        """Return how many segments were kept or dropped (and why), and trimmed per model."""
        return {'train': self.train_segments.counts.as_dict(),
                'evaluate': self.eval_segments.counts.as_dict(),
                'trimmed': {m: f.segments_trimmed for m, f in self.fits.items()}}

    def fitted_values(self) -> dict[str, dict[str, float]]:
        return {name: dict(fit.values) for name, fit in self.fits.items()}


def result_to_parameters(result: CalibrationResult, base: Mapping[str, Any] | None = None,
                         allow_invalid: bool = False) -> dict[str, Any]:
    """Flat parameters for ``write_params_file``: base values, then the calibration on top.

    model = the best model; every valid fitted model's parameters as models.<m>.<p>; its noise
    rates with models.<m>.noise.calibrated = True. Invalid fits (not converged, on a bound, or
    not observable: C14/C16) are not written; with ``allow_invalid`` they are written anyway.
    Raises FitError when no model besides ideal_dd could be calibrated (unless allowed).
    """
    flat = dict(base or {})
    flat['wheel_radius'] = float(result.geometry.wheel_radius)
    flat['track_width'] = float(result.geometry.track_width)
    written = []
    for name, fit in result.fits.items():
        if not (fit.valid or allow_invalid):
            continue
        for param, value in fit.values.items():
            flat[f'models.{name}.{param}'] = float(value)
        noise = result.noise.get(name)
        if noise is not None:
            flat[f'models.{name}.noise.calibrated'] = True
            for spec in NOISE_SPECS:
                flat[f'models.{name}.noise.{spec.name}'] = float(getattr(noise.noise, spec.name))
            if (fit.covariance is not None and fit.covariance.size
                    and result.options.parameter_covariance):
                flat[f'models.{name}.parameter_covariance'] = [
                    float(v) for v in np.asarray(fit.covariance, dtype=float).ravel()]
        written.append(name)
    trained = [m for m in written if get_model(m).params]
    if not trained and not allow_invalid:
        problems = '; '.join(w for w in result.warnings) or 'see the fit status'
        raise FitError(f'no kinematic model could be calibrated from this data: {problems}')
    flat['model'] = result.best
    flat['interval'] = result.options.interval
    if result.gyro is not None:
        flat.update(gyro_parameters(result.gyro))
    return flat
