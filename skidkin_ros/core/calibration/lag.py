"""The wheel-to-reference lag rule: one home for the offline diagnosis and the online check.

A reference (ground truth, lidar odometry, a SLAM) stamps the same motion ``lag`` seconds after
the wheels (positive: the reference's motion lags the wheels). The rule, for a cost ``cost(lag)``
that is the mean squared velocity residual between the reference and the wheel model read at
``t - lag`` (:func:`velocity_cost`: v_x, v_y and the yaw rate scaled by b/2 to metres per second):

1. **Scan** (:func:`scan`): every ``COARSE_STEPS`` x ``LAG_STEP_S`` (50 ms) from -range to
   +range, then every ``LAG_STEP_S`` (10 ms) within 50 ms of the coarse minimum; the best lag is
   the smallest cost (the curve is smooth in the lag: this costs a third of scanning every step).
2. **Uncertainty** (:func:`lag_sigma`): a parabola through the fine points around the best lag
   gives the curvature a of the mean cost; the residual's variance is the cost at the best lag,
   so one standard deviation is sqrt(cost_min / (count a)) (Gauss-Newton on ``count`` velocity
   residuals), at least half a step. A flat curve (no speed or yaw-rate change in the data:
   nothing to align) gives an infinite sigma.

:func:`skidkin_ros.core.calibration.diagnosis.tracing.lag_scan` runs it over a recording's pose
samples; :mod:`skidkin_ros.core.online.delay` over a bounded recent window while driving.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

__all__ = ['LAG_STEP_S', 'COARSE_STEPS', 'scan', 'velocity_cost', 'lag_sigma']

LAG_STEP_S = 0.01
COARSE_STEPS = 5


def velocity_cost(residual: np.ndarray, track_width: float) -> float:
    """Return the mean squared velocity residual (N, 3): v_x, v_y m/s, yaw rate x b/2."""
    scale = np.array([1.0, 1.0, track_width / 2])
    return float(np.mean(((residual * scale) ** 2).sum(axis=1)))


def scan(cost: Callable[[float], float], lag_range_s: float
         ) -> tuple[float, np.ndarray, np.ndarray]:
    """Return the best lag (s), the lags scanned and their costs (step 1)."""
    scores: dict[float, float] = {}

    def score(lag: float) -> float:
        lag = round(lag / LAG_STEP_S) * LAG_STEP_S
        if lag not in scores:
            scores[lag] = cost(float(lag))
        return scores[lag]

    coarse = LAG_STEP_S * COARSE_STEPS
    reach = round(lag_range_s / coarse)
    best = min((k * coarse for k in range(-reach, reach + 1)), key=score)
    for k in range(-COARSE_STEPS + 1, COARSE_STEPS):
        lag = best + k * LAG_STEP_S
        if abs(lag) <= lag_range_s + 1e-9:
            score(lag)
    lags = np.array(sorted(scores))
    curve = np.array([scores[lag] for lag in lags])
    return float(lags[int(np.argmin(curve))]), lags, curve


def lag_sigma(lags: np.ndarray, curve: np.ndarray, count: int) -> float:
    """Return one standard deviation (s) of the best lag from the curve's curvature (step 2)."""
    best = int(np.argmin(curve))
    near = np.abs(lags - lags[best]) <= (COARSE_STEPS - 1) * LAG_STEP_S + 1e-9
    if near.sum() < 3 or count < 2:
        return math.inf
    a = float(np.polyfit(lags[near] - lags[best], curve[near], 2)[0])
    if not a > 0.0:
        return math.inf
    return max(math.sqrt(max(float(curve[best]), 0.0) / (count * a)), 0.5 * LAG_STEP_S)
