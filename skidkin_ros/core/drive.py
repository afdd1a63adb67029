"""Core data types: wheel samples, a pose track, and a drive that pairs them.

Times are integer nanoseconds (``t_ns``) everywhere; convert to float seconds only for maths.
A source (a bag, a trajectory table) yields a list of ``Drive`` objects: each is one continuous
stretch of driving with its own ground-truth frame (a table's ``segment`` column starts a new one).

Ground truth is often sample-and-held (ICP at 10 Hz held onto a 20 Hz grid): a repeated pose is
stale, not a new measurement. :func:`fresh_pose_mask` is the one rule that tells the refreshed
rows; the table reader drops the held ones and the diagnosis differentiates only the fresh ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from skidkin_ros.errors import DataError

__all__ = ['WheelSamples', 'PoseTrack', 'ImuSamples', 'Drive', 'fresh_pose_mask', 'path_length_m']


def _as_time(t_ns, what: str) -> np.ndarray:
    t = np.asarray(t_ns)
    if t.ndim != 1:
        raise DataError(f'{what}: expected a 1-D array of stamps in ns, got shape {t.shape}')
    return t.astype(np.int64)


def _check_sorted(t: np.ndarray, what: str) -> None:
    if t.size > 1 and np.any(np.diff(t) < 0):
        raise DataError(f'{what}: stamps must be non-decreasing; sort or clean the data first')


def path_length_m(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Return the cumulative planar distance (m) along the points (x, y), starting at 0."""
    return np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])


def fresh_pose_mask(x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Return True for rows whose pose differs from the previous row (first row always True)."""
    same = (np.diff(x) == 0.0) & (np.diff(y) == 0.0) & (np.diff(yaw) == 0.0)
    return np.concatenate([[True], ~same])


@dataclass(frozen=True)
class WheelSamples:
    """Measured wheel angular velocities (rad/s), one row per sample, held until the next."""

    t_ns: np.ndarray
    omega_l: np.ndarray
    omega_r: np.ndarray

    def __post_init__(self) -> None:
        t = _as_time(self.t_ns, 'wheel samples')
        object.__setattr__(self, 't_ns', t)
        for name in ('omega_l', 'omega_r'):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != t.shape:
                raise DataError(f'wheel samples: {name} has shape {value.shape}, '
                                f'stamps have {t.shape}')
            object.__setattr__(self, name, value)
        _check_sorted(t, 'wheel samples')

    def __len__(self) -> int:
        return int(self.t_ns.size)

    @property
    def t_s(self) -> np.ndarray:
        return (self.t_ns - (self.t_ns[0] if len(self) else 0)) * 1e-9

    def between(self, t0_ns: int, t1_ns: int) -> 'WheelSamples':
        """Return the samples with t0 <= t <= t1."""
        keep = (self.t_ns >= t0_ns) & (self.t_ns <= t1_ns)
        return WheelSamples(self.t_ns[keep], self.omega_l[keep], self.omega_r[keep])


@dataclass(frozen=True)
class PoseTrack:
    """Planar poses of base_link in a fixed frame: x, y (m), yaw (rad, unwrapped).

    ``valid`` marks poses the ground-truth pipeline trusts (False: flagged, e.g. an implausible
    ICP increment); segments touching an invalid pose are excluded from fitting and evaluation.
    ``yaw_variance`` (rad^2, NaN where not given): the heading variance the source published
    (a pose covariance's yaw entry); online calibration reads it (GNSS: no heading), nothing
    else does.
    """

    t_ns: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    valid: np.ndarray | None = None
    yaw_variance: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = _as_time(self.t_ns, 'pose track')
        object.__setattr__(self, 't_ns', t)
        for name in ('x', 'y', 'yaw'):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != t.shape:
                raise DataError(f'pose track: {name} has shape {value.shape}, stamps have '
                                f'{t.shape}')
            object.__setattr__(self, name, value)
        valid = (np.ones(t.shape, dtype=bool) if self.valid is None
                 else np.asarray(self.valid, dtype=bool))
        object.__setattr__(self, 'valid', valid)
        if self.yaw_variance is not None:
            variance = np.asarray(self.yaw_variance, dtype=float)
            if variance.shape != t.shape:
                raise DataError(f'pose track: yaw_variance has shape {variance.shape}, stamps '
                                f'have {t.shape}')
            object.__setattr__(self, 'yaw_variance', variance)
        _check_sorted(t, 'pose track')

    def __len__(self) -> int:
        return int(self.t_ns.size)

    @property
    def poses(self) -> np.ndarray:
        return np.stack([self.x, self.y, self.yaw], axis=-1)

    def path_length(self) -> np.ndarray:
        """Cumulative distance travelled along the track (m), starting at 0."""
        return path_length_m(self.x, self.y)

    def interpolate(self, t_ns) -> np.ndarray:
        """Poses (..., 3) at the given stamps, linear in x, y and unwrapped yaw."""
        t = np.asarray(t_ns, dtype=np.int64)
        ref = self.t_ns
        return np.stack([np.interp(t, ref, self.x), np.interp(t, ref, self.y),
                         np.interp(t, ref, self.yaw)], axis=-1)


@dataclass(frozen=True)
class ImuSamples:
    """Gyro yaw rate (rad/s) and, when present, body accelerations (m/s^2)."""

    t_ns: np.ndarray
    yaw_rate: np.ndarray
    accel_x: np.ndarray | None = None
    accel_y: np.ndarray | None = None


@dataclass(frozen=True)
class Drive:
    """One continuous drive: wheel samples and the ground truth on its own time base."""

    name: str
    wheels: WheelSamples
    truth: PoseTrack | None
    imu: ImuSamples | None = None
    meta: Mapping[str, Any] = field(default_factory=dict)

    def duration_s(self) -> float:
        if len(self.wheels) < 2:
            return 0.0
        return float(self.wheels.t_ns[-1] - self.wheels.t_ns[0]) * 1e-9
