"""Trace the residuals: what they correlate with, and how far the motion lags the wheels.

1. **Correlations.** Pearson r of each residual component (v_x, v_y, omega) with every signal of
   :func:`~skidkin_ros.core.calibration.diagnosis.residuals.pose_samples` over the valid poses
   (NaN where fewer than 10 values or a constant): the report's leads.
2. **Lag scan.** The refitted base model runs with a time offset from -``lag_range_s`` to
   +``lag_range_s`` (every 50 ms, then every 10 ms within 50 ms of the best); at each offset,
   the mean squared velocity residual (yaw rate scaled by b/2 to metres per second). The best
   offset is the wheel-to-ground-truth lag: it is reported and starts the timing extensions' fits
   (:class:`skidkin_ros.core.kinematics.extensions.FitHints`).
3. **What is left.** After the selection, the final model's residual is traced again
   (:func:`residual_leads`): for each component and signal, the share of the whole velocity
   error (v_x, v_y and omega b/2 squared, summed) that a straight line in the signal explains
   (r^2 times the component's spread). A share of at least ``UNEXPLAINED_SHARE`` is reported as
   an unexplained residual, so a miss is said, not silent.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Mapping, Sequence

import numpy as np

from skidkin_ros.core.calibration.diagnosis.options import DiagnosisOptions
from skidkin_ros.core.calibration.diagnosis.residuals import (COMPONENTS, model_rollouts,
                                                              pose_residuals, PoseSamples)
from skidkin_ros.core.calibration.diagnosis.state import ModelState
from skidkin_ros.core.calibration.lag import (COARSE_STEPS, LAG_STEP_S,  # noqa: F401
                                              scan, velocity_cost)
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.kinematics.augmented import AugmentedModel
from skidkin_ros.core.kinematics.models import BoundModel
from skidkin_ros.core.kinematics.specs import Geometry

__all__ = ['Trace', 'ResidualLead', 'correlations', 'lag_scan', 'residual_leads',
           'UNEXPLAINED_SHARE']

# A signal that explains at least this share of the velocity error left is reported.
UNEXPLAINED_SHARE = 0.1
# Signals that are the same quantity under another name: one lead per quantity.
_SAME = {'omega_l': 'wheel', 'omega_r': 'wheel', 'wheel_sum': 'body_speed',
         'wheel_diff': 'yaw_rate', 'd_wheel_sum': 'd_body_speed', 'd_wheel_diff': 'd_yaw_rate',
         'speed_sin_heading': 'heading', 'speed_cos_heading': 'heading'}
# Signals a residual follows together (a slope pushes along its own direction, a combination of
# the heading's sine and cosine): the lead is their joint fit, named by the quantity.
_PAIRS = {'heading': ('speed_sin_heading', 'speed_cos_heading')}


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


def correlations(residual: np.ndarray, valid: np.ndarray,
                 signals: Mapping[str, np.ndarray]) -> dict[tuple[str, str], float]:
    """Return {(component, signal): Pearson r} over the valid, finite poses (step 1)."""
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


def lag_scan(drives: Sequence[Drive], samples: PoseSamples, state: ModelState,
             base_name: str, geometry: Geometry, options: DiagnosisOptions
             ) -> tuple[float, tuple[np.ndarray, np.ndarray]]:
    """Refit the velocity residual over offsets; return the best offset and the curve (step 2).

    The rule (scan, cost) is :mod:`skidkin_ros.core.calibration.lag`'s, shared with the online
    check of the reference's delay.
    """
    base = state.bind(base_name, geometry)
    base = base if isinstance(base, BoundModel) else base.base
    # a time offset moves the stamps the model's poses are read at, not the poses: one rollout
    rollouts = model_rollouts(drives, samples, AugmentedModel(base_name, ['time_offset']).bind(
        base, {'time_offset': {'offset_s': 0.0}}), options)

    def cost(lag: float) -> float:
        source = AugmentedModel(base_name, ['time_offset']).bind(
            base, {'time_offset': {'offset_s': lag}})
        residual, valid = pose_residuals(drives, samples, source, options, rollouts)
        return velocity_cost(residual[valid], geometry.track_width)

    best, lags, curve = scan(cost, options.lag_range_s)
    return best, (lags, curve)


@dataclass(frozen=True)
class ResidualLead:
    """A signal a residual component still follows: Pearson r and the share of the error."""

    component: str
    signal: str
    r: float
    share: float


def _joint_r(target: np.ndarray, columns: Sequence[np.ndarray]) -> float:
    """Return the multiple correlation (>= 0) of ``target`` with a linear fit on ``columns``."""
    x = np.column_stack(columns)
    ok = np.isfinite(target) & np.all(np.isfinite(x), axis=1)
    if ok.sum() < 10 or np.std(target[ok]) == 0:
        return math.nan
    x = np.column_stack([x[ok], np.ones(ok.sum())])
    y = target[ok] - target[ok].mean()
    fit = x @ np.linalg.lstsq(x, y, rcond=None)[0]
    return float(math.sqrt(max(0.0, min(1.0, (fit @ fit) / (y @ y)))))


def residual_leads(residual: np.ndarray, valid: np.ndarray, signals: Mapping[str, np.ndarray],
                   geometry: Geometry, min_share: float = UNEXPLAINED_SHARE
                   ) -> tuple[ResidualLead, ...]:
    """Return the signals that explain at least ``min_share`` of the velocity error (step 3).

    Strongest first, at most one per component and per quantity (``wheel_sum`` and
    ``body_speed`` are one).
    """
    scale = np.array([1.0, 1.0, geometry.track_width / 2])
    scaled = residual[valid] * scale
    total = float((scaled ** 2).sum())
    if scaled.shape[0] < 10 or not total > 0.0:
        return ()
    spread = ((scaled - scaled.mean(axis=0)) ** 2).sum(axis=0)
    leads = []
    for (component, signal), r in correlations(residual, valid, signals).items():
        if math.isfinite(r):
            share = r * r * float(spread[COMPONENTS.index(component)]) / total
            leads.append(ResidualLead(component, signal, r, share))
    for name, pair in _PAIRS.items():
        if not all(p in signals for p in pair):
            continue
        for c, component in enumerate(COMPONENTS):
            r = _joint_r(residual[valid, c], [np.asarray(signals[p])[valid] for p in pair])
            if math.isfinite(r):
                leads.append(ResidualLead(component, name, r, r * r * float(spread[c]) / total))
    leads.sort(key=lambda lead: -lead.share)
    kept: list[ResidualLead] = []
    for lead in leads:
        if lead.share < min_share:
            break
        quantity = _SAME.get(lead.signal, lead.signal)
        if any(k.component == lead.component or _SAME.get(k.signal, k.signal) == quantity
               for k in kept):
            continue
        kept.append(lead)
    return tuple(kept)
