"""Relative errors per metre (Baril et al. 2020, after KITTI/Geiger 2012).

On evaluation segments of horizon h_e (cut on the ground truth, the same for every model):

- eps_t (m/m) = |end-position error| / ground-truth path length of the segment;
- eps_theta (deg/m) = |wrapped heading error| (deg) / path length.

Segments shorter than ``min_path_m`` (spins in place) are left out of these per-metre figures:
dividing by a near-zero path would dominate every statistic.

:func:`relative_errors` is the one place the two figures are computed: for the calibrated models,
the diagnosis's before/after table, the studies, and any odometry output against ground truth
(:func:`relative_pose_errors`, e.g. what the node published in ``skidkin demo``).
:func:`motion_errors` is the one place an estimated motion is compared with the true one (the
relative pose errors here, the simulator's ground-truth accuracy).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Mapping

import numpy as np

from skidkin_ros.core.calibration.fitting import segment_errors
from skidkin_ros.core.calibration.segments import segment_frame_error, SegmentSet
from skidkin_ros.core.drive import path_length_m, PoseTrack
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.errors import DataError

__all__ = [
    'relative_errors',
    'ErrorStats',
    'ModelEvaluation',
    'evaluate_model',
    'evaluate_models',
    'relative_pose_errors',
    'motion_errors',
    'WindowEnd',
    'window_end_errors',
]


def relative_errors(errors: np.ndarray, path_m: np.ndarray,
                    min_path_m: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Return eps_t (m/m) and eps_theta (deg/m) of the segments at least min_path_m long.

    ``errors``: (N, 3) end-pose errors in each segment's start frame (m, m, rad, yaw wrapped);
    ``path_m``: (N,) ground-truth path lengths. The one place these figures are computed.
    """
    scored = path_m >= min_path_m
    path = path_m[scored]
    return (np.hypot(errors[scored, 0], errors[scored, 1]) / path,
            np.degrees(np.abs(errors[scored, 2])) / path)


@dataclass(frozen=True)
class ErrorStats:
    """Median, quartiles, 90th percentile, mean and count of one error metric."""

    median: float
    q25: float
    q75: float
    p90: float
    mean: float
    count: int

    @classmethod
    def of(cls, values: np.ndarray) -> 'ErrorStats':
        values = np.asarray(values, dtype=float)
        if values.size == 0:
            nan = math.nan
            return cls(nan, nan, nan, nan, nan, 0)
        q25, med, q75, p90 = np.percentile(values, [25, 50, 75, 90])
        return cls(float(med), float(q25), float(q75), float(p90), float(values.mean()),
                   int(values.size))


@dataclass(frozen=True)
class ModelEvaluation:
    """Per-segment errors of one model on the evaluation segments, and their statistics."""

    model: str
    errors: np.ndarray          # (N, 3) start-frame errors (m, m, rad) on every segment
    scored: np.ndarray          # (N,) True where the segment enters eps_t / eps_theta
    eps_t: np.ndarray           # (M,) m/m on the scored segments
    eps_theta_deg: np.ndarray   # (M,) deg/m on the scored segments
    stats_t: ErrorStats
    stats_theta: ErrorStats


def evaluate_model(name: str, values: Mapping[str, float], geometry: Geometry,
                   segments: SegmentSet, min_path_m: float = 0.1) -> ModelEvaluation:
    """Score one model with the given parameter values on the segments."""
    model = get_model(name)
    k = model.vector(dict(values), geometry)
    errors = segment_errors(model, k, geometry, segments)
    scored = segments.path_m >= min_path_m
    eps_t, eps_theta = relative_errors(errors, segments.path_m, min_path_m)
    return ModelEvaluation(name, errors, scored, eps_t, eps_theta, ErrorStats.of(eps_t),
                           ErrorStats.of(eps_theta))


def evaluate_models(values: Mapping[str, Mapping[str, float]], geometry: Geometry,
                    segments: SegmentSet, min_path_m: float = 0.1) -> dict[str, ModelEvaluation]:
    """Score every model of ``values`` ({model: {param: value}}) on the same segments."""
    if len(segments) == 0:
        raise DataError('no evaluation segment: drive more, or shorten h_e')
    return {name: evaluate_model(name, vals, geometry, segments, min_path_m)
            for name, vals in values.items()}


@dataclass(frozen=True)
class WindowEnd:
    """Median errors at the end of held-out windows (heading drift is what odometry must hold)."""

    yaw_rad: float        # median |heading error| at the window ends
    position_m: float     # median |position error| at the window ends
    windows: int


def window_end_errors(name: str, values: Mapping[str, float], geometry: Geometry,
                      windows: SegmentSet) -> WindowEnd:
    """Return the median heading and position errors at the end of each window segment."""
    model = get_model(name)
    errors = segment_errors(model, model.vector(dict(values), geometry), geometry, windows)
    if len(windows) == 0:
        return WindowEnd(math.nan, math.nan, 0)
    return WindowEnd(float(np.median(np.abs(errors[:, 2]))),
                     float(np.median(np.hypot(errors[:, 0], errors[:, 1]))), len(windows))


def relative_pose_errors(t_ns: np.ndarray, estimate: np.ndarray, truth: PoseTrack,
                         horizon_m: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Relative errors of any odometry output against ground truth, per metre (evo-style RPE).

    ``estimate`` (N, 3) are poses at ``t_ns`` (e.g. what the node published). Windows of
    ``horizon_m`` travelled on the ground-truth path, non-overlapping; the estimate's relative
    motion over each window is compared with the truth's, in the window's start frame. Returns
    (eps_t in m/m, eps_theta in deg/m).
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    estimate = np.asarray(estimate, dtype=float)
    inside = (t_ns >= truth.t_ns[0]) & (t_ns <= truth.t_ns[-1])
    t_ns, estimate = t_ns[inside], estimate[inside]
    true = truth.interpolate(t_ns)
    path = path_length_m(true[:, 0], true[:, 1])
    starts, ends = [], []
    a = 0
    while a < len(t_ns) - 1:
        b = int(np.searchsorted(path, path[a] + horizon_m, side='left'))
        if b >= len(t_ns):
            break
        starts.append(a)
        ends.append(b)
        a = b
    if not starts:
        return np.empty(0), np.empty(0)
    a_idx, b_idx = np.array(starts), np.array(ends)
    errors = motion_errors(estimate[a_idx], estimate[b_idx], true[a_idx], true[b_idx])
    # Every window is at least horizon_m > 0 long: none is left out.
    return relative_errors(errors, path[b_idx] - path[a_idx], min_path_m=0.0)


def motion_errors(estimate_start: np.ndarray, estimate_end: np.ndarray, true_start: np.ndarray,
                  true_end: np.ndarray) -> np.ndarray:
    """Return the (N, 3) errors of estimated motions start -> end against the true ones.

    Poses (N, 3): x, y (m), yaw (rad). The estimate's motion, in its own start frame, is replayed
    from the true start pose; the error is :func:`segment_frame_error`'s (true - replayed end, in
    the true start frame: m, m, rad; yaw wrapped).
    """
    c, s = np.cos(estimate_start[:, 2]), np.sin(estimate_start[:, 2])
    dx = estimate_end[:, 0] - estimate_start[:, 0]
    dy = estimate_end[:, 1] - estimate_start[:, 1]
    local = np.stack([c * dx + s * dy, -s * dx + c * dy,
                      estimate_end[:, 2] - estimate_start[:, 2]], axis=-1)
    ct, st = np.cos(true_start[:, 2]), np.sin(true_start[:, 2])
    replayed = np.stack([true_start[:, 0] + ct * local[:, 0] - st * local[:, 1],
                         true_start[:, 1] + st * local[:, 0] + ct * local[:, 1],
                         true_start[:, 2] + local[:, 2]], axis=-1)
    return segment_frame_error(true_start, true_end, replayed)
