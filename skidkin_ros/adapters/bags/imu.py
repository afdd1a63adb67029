"""Read the gyro yaw rate and planar accelerations of a sensor_msgs/Imu topic."""

from __future__ import annotations

import math

import numpy as np

from skidkin_ros.adapters.bags.common import IMU, stamp_ns
from skidkin_ros.core.drive import ImuSamples
from skidkin_ros.errors import RecordingError


class ImuMixin:
    """read_imu."""

    # -- imu -------------------------------------------------------------------------------------
    def read_imu(self, topic: str | None = None) -> ImuSamples:
        """Return gyro yaw rate (rad/s, angular_velocity.z) and accel x / y (m/s^2)."""
        chosen = self.select(IMU, topic, 'imu')
        rows: list[tuple[int, float, float, float]] = []
        for _, msg in self.messages(chosen):
            row = (stamp_ns(msg.header), float(msg.angular_velocity.z),
                   float(msg.linear_acceleration.x), float(msg.linear_acceleration.y))
            if not all(math.isfinite(v) for v in row[1:]):
                self._drop(chosen, 'non-finite value')
                continue
            rows.append(row)
        if not rows:
            raise RecordingError(f'imu: no valid message on {chosen} ({self._reasons(chosen)})')
        t = np.array([r[0] for r in rows], dtype=np.int64)
        values = np.array([r[1:] for r in rows], dtype=np.float64)
        keep = self._keep_in_order(chosen, t)
        values = values[keep]
        return ImuSamples(t[keep], values[:, 0], values[:, 1], values[:, 2])
