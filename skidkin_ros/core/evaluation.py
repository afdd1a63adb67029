"""Relative errors per metre (Baril et al. 2020, after KITTI/Geiger 2012) and hold-out splits.

On evaluation segments of horizon h_e (cut on the ground truth, the same for every model):

- eps_t (m/m) = |end-position error| / ground-truth path length of the segment;
- eps_theta (deg/m) = |wrapped heading error| (deg) / path length.

Segments shorter than ``min_path_m`` (spins in place) are left out of these per-metre figures:
dividing by a near-zero path would dominate every statistic.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import math
from typing import Mapping, Sequence

import numpy as np

from skidkin_ros.core.drive import Drive, ImuSamples, PoseTrack, WheelSamples
from skidkin_ros.core.fitting import segment_errors
from skidkin_ros.core.models import get_model
from skidkin_ros.core.segments import segment_frame_error, SegmentSet
from skidkin_ros.core.specs import Geometry
from skidkin_ros.errors import DataError, ParameterError

__all__ = [
    'ErrorStats',
    'ModelEvaluation',
    'evaluate_model',
    'evaluate_models',
    'split_holdout',
    'HOLDOUT_MODES',
    'relative_pose_errors',
    'resolve_holdout',
]

HOLDOUT_MODES = ('auto', 'drive', 'time')


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
    path = segments.path_m[scored]
    eps_t = np.hypot(errors[scored, 0], errors[scored, 1]) / path
    eps_theta = np.degrees(np.abs(errors[scored, 2])) / path
    return ModelEvaluation(name, errors, scored, eps_t, eps_theta, ErrorStats.of(eps_t),
                           ErrorStats.of(eps_theta))


def evaluate_models(values: Mapping[str, Mapping[str, float]], geometry: Geometry,
                    segments: SegmentSet, min_path_m: float = 0.1) -> dict[str, ModelEvaluation]:
    """Score every model of ``values`` ({model: {param: value}}) on the same segments."""
    if len(segments) == 0:
        raise DataError('no evaluation segment: drive more, or shorten h_e')
    return {name: evaluate_model(name, vals, geometry, segments, min_path_m)
            for name, vals in values.items()}


def _time_slice(drive: Drive, t0_ns: int, t1_ns: int, suffix: str) -> Drive:
    wheels = drive.wheels.between(t0_ns, t1_ns)
    truth = drive.truth
    if truth is not None:
        keep = (truth.t_ns >= t0_ns) & (truth.t_ns <= t1_ns)
        truth = PoseTrack(truth.t_ns[keep], truth.x[keep], truth.y[keep], truth.yaw[keep],
                          truth.valid[keep])
    imu = drive.imu
    if imu is not None:
        keep = (imu.t_ns >= t0_ns) & (imu.t_ns <= t1_ns)
        imu = ImuSamples(imu.t_ns[keep], np.asarray(imu.yaw_rate)[keep])
    return replace(drive, name=f'{drive.name}{suffix}', wheels=WheelSamples(
        wheels.t_ns, wheels.omega_l, wheels.omega_r), truth=truth, imu=imu)


def split_holdout(drives: Sequence[Drive], every: int = 3, mode: str = 'auto',
                  block_s: float = 60.0, key: str | None = None
                  ) -> tuple[list[Drive], list[Drive]]:
    """Split drives into (train, evaluate) deterministically, when no evaluation drive is given.

    - ``key`` (e.g. 'calib_step'): a drive goes to evaluation when ``int(meta[key]) % every ==
      every - 1`` (every=2: odd values evaluate, even values train; the Husky table split);
    - mode 'drive': every ``every``-th drive (the last of each group) evaluates;
    - mode 'time': each drive is cut into blocks of ``block_s`` seconds and every ``every``-th
      block evaluates (a block boundary loses at most one segment on each side);
    - mode 'auto': 'drive' when there are at least ``2 * every`` drives, else 'time'.
    """
    if every < 2:
        raise ParameterError(f'every must be >= 2 (one in every blocks evaluates), got {every}')
    if mode not in HOLDOUT_MODES:
        raise ParameterError(f'hold-out mode must be one of {HOLDOUT_MODES}, got {mode!r}')
    if not drives:
        raise DataError('no drive to split')
    if key is not None:
        missing = [d.name for d in drives if key not in d.meta]
        if missing:
            raise DataError(f'drive(s) {missing[:3]} have no {key!r} in their metadata; '
                            'split by drive or time instead')
        train = [d for d in drives if int(d.meta[key]) % every != every - 1]
        evaluate = [d for d in drives if int(d.meta[key]) % every == every - 1]
        return train, evaluate
    if mode == 'auto':
        mode = 'drive' if len(drives) >= 2 * every else 'time'
    if mode == 'drive':
        return ([d for i, d in enumerate(drives) if i % every != every - 1],
                [d for i, d in enumerate(drives) if i % every == every - 1])
    if not block_s > 0:
        raise ParameterError(f'block_s must be > 0 s, got {block_s!r}')
    train, evaluate = [], []
    block_ns = int(block_s * 1e9)
    for drive in drives:
        if len(drive.wheels) == 0:
            continue
        t0 = int(drive.wheels.t_ns[0])
        t_end = int(drive.wheels.t_ns[-1])
        # A drive shorter than 2 * every blocks still gives two evaluation blocks.
        step_ns = max(1, min(block_ns, (t_end - t0) // (2 * every)))
        for index, start in enumerate(range(t0, t_end + 1, step_ns)):
            part = _time_slice(drive, start, min(start + step_ns - 1, t_end), f'@{index}')
            (evaluate if index % every == every - 1 else train).append(part)
    return train, evaluate


def resolve_holdout(train: Sequence[Drive], evaluate: Sequence[Drive] | None, every: int,
                    mode: str, block_s: float, key: str | None
                    ) -> tuple[list[Drive], list[Drive], str]:
    """Return (train, evaluate, how): the given split, or a deterministic hold-out of train."""
    if evaluate is not None:
        return list(train), list(evaluate), 'given'
    train, evaluate = split_holdout(train, every, mode, block_s, key)
    return train, evaluate, f'held out 1 in {every} ({key or mode})'


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
    path = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(true[:, 0]),
                                                     np.diff(true[:, 1])))])
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
    est_a, est_b = estimate[a_idx], estimate[b_idx]
    # the estimate's motion a -> b, replayed from the true start pose
    c, s = np.cos(est_a[:, 2]), np.sin(est_a[:, 2])
    dx, dy = est_b[:, 0] - est_a[:, 0], est_b[:, 1] - est_a[:, 1]
    local = np.stack([c * dx + s * dy, -s * dx + c * dy, est_b[:, 2] - est_a[:, 2]], axis=-1)
    start = true[a_idx]
    ct, st = np.cos(start[:, 2]), np.sin(start[:, 2])
    predicted = np.stack([start[:, 0] + ct * local[:, 0] - st * local[:, 1],
                          start[:, 1] + st * local[:, 0] + ct * local[:, 1],
                          start[:, 2] + local[:, 2]], axis=-1)
    errors = segment_frame_error(start, true[b_idx], predicted)
    length = path[b_idx] - path[a_idx]
    return (np.hypot(errors[:, 0], errors[:, 1]) / length,
            np.degrees(np.abs(errors[:, 2])) / length)
