"""Offline prediction: what running the odometer over recorded samples gives, and its feeds.

:class:`Prediction` is the result of :meth:`~skidkin_ros.core.odometry.odometer.Odometer.predict`
(and :func:`~skidkin_ros.core.odometry.odometer.predict_wheels`): the pose, twist, status and
covariance after every wheel sample. The feeds hand recorded reference poses and gyro samples to
the odometer in the order the node gets them, so the offline prediction and the node agree.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass
import itertools
from typing import Any

import numpy as np

from skidkin_ros.core.drive import ImuSamples, PoseTrack
from skidkin_ros.core.odometry.gyro import GyroAid
from skidkin_ros.core.odometry.integrator import SampleStatus
from skidkin_ros.core.timeunits import NS_PER_S

__all__ = ['Prediction']


@dataclass(frozen=True)
class Prediction:
    """Pose after every wheel sample (x, y, yaw), the held twist, and what happened to it.

    ``pose_covariances``: the pose covariance the node publishes after every sample (6 x 6).

    ``t_ns`` are the stamps the node publishes: the sample stamps plus ``offset_ns``, the time
    offset of an augmented model (0 for the five base models).
    """

    t_ns: np.ndarray
    poses: np.ndarray
    twists: np.ndarray
    status: tuple[SampleStatus, ...]
    offset_ns: int = 0
    pose_covariances: np.ndarray | None = None  # (N, 6, 6): what the node publishes
    covariances: np.ndarray | None = None   # (N, 3, 3) pose covariance, with ``restarts``
    imu_gain: np.ndarray | None = None      # (N,) the learned yaw-rate gain, with ``restarts``

    @property
    def accepted(self) -> np.ndarray:
        return np.array([s.accepted for s in self.status], dtype=bool)


class _ReferenceFeed:
    """Offline: hands recorded reference poses to the odometer in the order the node gets them."""

    def __init__(self, odometer: Any, track: PoseTrack | None) -> None:
        # odometer: the Odometer (typed loosely: the odometer module imports this one)
        self.odometer = odometer
        if track is None or len(track) == 0:
            self.rows: list[tuple] = []
        else:
            variance = (np.full(len(track), np.nan) if track.yaw_variance is None
                        else track.yaw_variance)
            # the heading's variance as the node reads it from the pose covariance (NaN: none)
            self.rows = list(zip(np.asarray(track.t_ns, dtype=np.int64).tolist(),
                                 np.asarray(track.x, dtype=float).tolist(),
                                 np.asarray(track.y, dtype=float).tolist(),
                                 np.asarray(track.yaw, dtype=float).tolist(),
                                 itertools.repeat(''), itertools.repeat(''),
                                 np.asarray(variance, dtype=float).tolist()))
        self.i = 0

    def until(self, t_ns: int) -> None:
        rows, n = self.rows, len(self.rows)
        while self.i < n and rows[self.i][0] <= t_ns:
            self.odometer.reference_sample(*rows[self.i])
            self.i += 1


class _GyroFeed:
    """Offline: hands recorded gyro samples to the buffer in the order the node gets them."""

    def __init__(self, gyro: GyroAid | None, imu: ImuSamples | None,
                 counters: collections.Counter[str]) -> None:
        self.gyro = gyro
        self.counters = counters
        if gyro is None or imu is None or len(imu.t_ns) == 0:
            self.t: list[int] = []
            self.rate: list[float] = []
        else:
            self.t = np.asarray(imu.t_ns, dtype=np.int64).tolist()
            self.rate = np.asarray(imu.yaw_rate, dtype=float).tolist()
            newest = gyro.buffer.newest_ns
            if newest is not None and self.t[0] <= newest:   # a new recording's clock
                gyro.buffer.clear()
        self.i = 0

    def _add(self) -> None:
        status = self.gyro.buffer.add(self.t[self.i], self.rate[self.i])
        self.counters['imu_' + status.value] += 1
        self.i += 1

    def until(self, t_ns: int) -> None:
        """Feed what has arrived by the wheel sample at t_ns, then what it waits for."""
        t, n = self.t, len(self.t)
        while self.i < n and t[self.i] <= t_ns:
            self._add()
        if self.i < n:
            ready = self.gyro.buffer.ready
            deadline = t_ns + self.gyro.params.max_wait * NS_PER_S
            while self.i < n and t[self.i] <= deadline and not ready(t_ns):
                self._add()
