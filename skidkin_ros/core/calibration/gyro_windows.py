"""The node's odometer run on held-out windows and segments: every imu.mode scored, window NEES.

:func:`segment_windows` picks the segments that can be run as windows (restarted from the true
pose at a wheel sample), :func:`run_windows` runs one odometer over them (errors and published
covariances at the window ends, :func:`window_nees`), and :func:`predict_drives` /
:func:`odometry_segment_errors` give the odometry's errors on segments.
:func:`evaluate_gyro_mode` runs the node's odometer (:meth:`Odometer.predict`, so exactly what the
node and ``skidkin predict`` do) over the drives in order, the learned gain and bias carried from
drive to drive, and scores the evaluation segments with the one :func:`relative_errors`.
The gyro's calibration that uses these windows is :mod:`skidkin_ros.core.calibration.gyro_fit`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Mapping, Sequence

import numpy as np

from skidkin_ros.core.calibration.evaluation import ErrorStats, ModelEvaluation, relative_errors
from skidkin_ros.core.calibration.noise_fit import mahalanobis, MIN_VARIANCE
from skidkin_ros.core.calibration.segments import segment_frame_error, SegmentSet
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.odometer import Odometer, Prediction
from skidkin_ros.errors import DataError

__all__ = ['segment_windows', 'window_poses', 'run_windows', 'window_nees', 'predict_drives',
           'odometry_segment_errors', 'ModeScore', 'evaluate_gyro_mode']


def segment_windows(drives: Sequence[Drive], segments: SegmentSet
                    ) -> dict[int, list[tuple[int, int, int]]]:
    """Return {drive index: [(i, j, k)]}: the segments k that can be run as windows.

    A window runs from wheel sample i to wheel sample j, the samples nearest the segment's start
    and end (within half a wheel period: a lidar's poses are never stamped on the wheel samples,
    a table's usually are), and overlaps no earlier one of its drive: the odometer restarts after
    sample i from the true pose at that sample with a zero covariance (``Odometer.predict``'s
    ``restarts``) and is read at j (:func:`window_poses` gives the true poses there).
    """
    windows: dict[int, list[tuple[int, int, int]]] = {}
    for k in range(len(segments)):
        d = int(segments.drive[k])
        t = drives[d].wheels.t_ns
        if len(t) < 2:
            continue
        half_period = 0.5 * float(np.median(np.diff(t)))
        i, j = (_nearest(t, int(s)) for s in (segments.t_a_ns[k], segments.t_b_ns[k]))
        if (j > i and abs(int(t[i]) - int(segments.t_a_ns[k])) <= half_period
                and abs(int(t[j]) - int(segments.t_b_ns[k])) <= half_period):
            windows.setdefault(d, []).append((i, j, k))
    for d, found in windows.items():
        kept, end = [], -1
        for i, j, k in sorted(found):
            if i >= end:
                kept.append((i, j, k))
                end = j
        windows[d] = kept
    return windows


def _nearest(t: np.ndarray, stamp: int) -> int:
    """Return the index of the stamp of ``t`` (sorted) nearest ``stamp``."""
    i = int(np.searchsorted(t, stamp))
    if i == len(t) or (i > 0 and stamp - int(t[i - 1]) < int(t[i]) - stamp):
        return i - 1
    return i


def window_poses(drive: Drive, segments: SegmentSet, window: tuple[int, int, int]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Return the true (start, end) poses of a window, at its wheel samples i and j.

    A segment end stamped on the wheel sample is the segment's own pose; otherwise the ground
    truth is interpolated to the wheel sample (linear in x, y and unwrapped yaw: at 10 Hz and
    walking speed, a fraction of a millimetre from the arc).
    """
    i, j, k = window
    t = drive.wheels.t_ns
    start = (segments.start[k] if t[i] == segments.t_a_ns[k]
             else drive.truth.interpolate(t[i]))
    end = segments.end[k] if t[j] == segments.t_b_ns[k] else drive.truth.interpolate(t[j])
    return np.asarray(start, dtype=float), np.asarray(end, dtype=float)


def run_windows(config: OdometryConfig, drives: Sequence[Drive], segments: SegmentSet,
                windows: Mapping[int, Sequence[tuple[int, int, int]]],
                ends_only: bool = False
                ) -> tuple[np.ndarray, np.ndarray, dict[int, Prediction]]:
    """Run ``config``'s odometer (one, the drives in order) over the windows of each drive.

    Return the start-frame errors (K, 3) and pose covariances (K, 3, 3) at the window ends, in
    the order of ``windows``, and the predictions by drive (their poses restart at each window).
    ``ends_only``: the predictions' covariances and gains are read out at the window ends only
    (NaN elsewhere; the same errors and covariances are returned, with less work).
    """
    odometer = Odometer.from_config(config)
    errors, covs, predictions = [], [], {}
    for d, found in windows.items():
        drive = drives[d]
        poses = [window_poses(drive, segments, window) for window in found]
        restarts = {i: start for (i, _, _), (start, _) in zip(found, poses)}
        ends = frozenset(j for _, j, _ in found) if ends_only else None
        pred = odometer.predict(drive.wheels, drive.truth.poses[0], drive.imu, restarts,
                                covariance_at=ends)
        predictions[d] = pred
        for (_, j, _), (start, end) in zip(found, poses):
            errors.append(segment_frame_error(start[None], end[None], pred.poses[j][None])[0])
            c, s = np.cos(start[2]), np.sin(start[2])
            rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
            covs.append(rot @ pred.covariances[j] @ rot.T)
    return np.array(errors).reshape(-1, 3), np.array(covs).reshape(-1, 3, 3), predictions


def window_nees(errors: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """Return e^T P^-1 e per window (P + MIN_VARIANCE I, as the noise fit checks it)."""
    covs = np.asarray(covs, dtype=float).reshape(-1, 3, 3) + MIN_VARIANCE * np.eye(3)
    return mahalanobis(covs, np.asarray(errors, dtype=float).reshape(-1, 3))


def predict_drives(config: OdometryConfig, drives: Sequence[Drive], model: str | None = None,
                   mode: str | None = None) -> list[Prediction]:
    """Return the odometry of each drive (started at its first true pose), in order.

    Each :class:`Prediction` holds the pose after every wheel sample and the stamp it is
    published at (the sample's plus a model's time offset: fault matrix C101). One odometer
    runs the drives one after the other (``mode`` replaces imu.mode), as one node would: its
    learned gain and bias carry over; a drive whose stamps restart starts a new gyro history.
    """
    if mode is not None:
        config = replace(config, values={**config.values, 'imu.mode': mode})
    odometer = Odometer.from_config(config, model)
    out = []
    for drive in drives:
        start = drive.truth.poses[0] if drive.truth is not None else (0.0, 0.0, 0.0)
        out.append(odometer.predict(drive.wheels, start, drive.imu))
    return out


def odometry_segment_errors(predictions: Sequence[Prediction], segments: SegmentSet
                            ) -> np.ndarray:
    """Return the (N, 3) start-frame end errors of the odometry on the segments.

    ``predictions[d]`` is the odometry of the drive ``segments.drive`` numbers d: its poses at
    its published stamps (a model's time offset included); its relative motion from t_a to t_b
    (interpolated at the segment ends) is replayed from the segment's true start pose.
    """
    errors = np.zeros((len(segments), 3))
    for k in range(len(segments)):
        pred = predictions[int(segments.drive[k])]
        t, est = pred.t_ns, pred.poses
        a, b = (np.array([np.interp(s, t, est[:, j]) for j in range(3)])
                for s in (segments.t_a_ns[k], segments.t_b_ns[k]))
        c, s = np.cos(a[2]), np.sin(a[2])
        dx, dy = b[0] - a[0], b[1] - a[1]
        local = (c * dx + s * dy, -s * dx + c * dy, b[2] - a[2])
        x0, y0, th0 = segments.start[k]
        ct, st = np.cos(th0), np.sin(th0)
        predicted = np.array([[x0 + ct * local[0] - st * local[1],
                               y0 + st * local[0] + ct * local[1], th0 + local[2]]])
        errors[k] = segment_frame_error(segments.start[k:k + 1], segments.end[k:k + 1],
                                        predicted)[0]
    return errors


@dataclass(frozen=True)
class ModeScore:
    """One model in one imu mode: segment errors, and the errors at each drive's end."""

    evaluation: ModelEvaluation
    end_position_m: ErrorStats     # |position error| at the drive's last true pose
    end_yaw_deg: ErrorStats        # |heading error| there
    nees: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per window (3 dof)


def evaluate_gyro_mode(config: OdometryConfig, drives: Sequence[Drive], segments: SegmentSet,
                       model: str, mode: str, min_path_m: float = 0.1) -> ModeScore:
    """Score ``model`` in imu ``mode`` on ``segments`` (cut on ``drives``), like the node runs.

    The relative motion the odometry predicts from t_a to t_b (poses at the wheel samples,
    interpolated at the segment ends) is replayed from the segment's true start pose. Each
    drive's odometry starts at its first true pose; its end error is taken at its last one
    (for the Husky table: the window-end errors). ``nees``: the published pose covariance
    against the error on every :func:`segment_windows` window (a second run, restarted at each
    window from its true pose with a zero covariance, the gain and bias carried on).
    """
    if mode != 'off' and not any(d.imu is not None for d in drives):
        raise DataError(f'imu mode {mode} needs gyro samples; the data has none (a table needs '
                        'the imu_yaw_rate column, a bag a sensor_msgs/Imu topic)')
    predictions = predict_drives(config, drives, model, mode)
    errors = odometry_segment_errors(predictions, segments)
    scored = segments.path_m >= min_path_m
    eps_t, eps_theta = relative_errors(errors, segments.path_m, min_path_m)
    evaluation = ModelEvaluation(f'{model} ({mode})', errors, scored, eps_t, eps_theta,
                                 ErrorStats.of(eps_t), ErrorStats.of(eps_theta))
    end_pos, end_yaw = [], []
    for drive, pred in zip(drives, predictions):
        truth = drive.truth
        if truth is None or len(truth) < 2:
            continue
        t_end = truth.t_ns[-1]
        at = np.array([np.interp(t_end, pred.t_ns, pred.poses[:, j]) for j in range(3)])
        end_pos.append(float(np.hypot(at[0] - truth.x[-1], at[1] - truth.y[-1])))
        end_yaw.append(float(np.degrees(abs((at[2] - truth.yaw[-1] + np.pi) % (2 * np.pi)
                                            - np.pi))))
    nees = np.zeros(0)
    scored_config = replace(config, model=model, values={**config.values, 'imu.mode': mode})
    windows = segment_windows(drives, segments)
    if scored_config.active_noise is not None and windows:
        errors, covs, _ = run_windows(scored_config, drives, segments, windows, ends_only=True)
        nees = window_nees(errors, covs)
    return ModeScore(evaluation, ErrorStats.of(np.array(end_pos)),
                     ErrorStats.of(np.array(end_yaw)), nees)
