"""Distance that `wheel_signal` position and auto read from a quantised encoder.

A 0.5 m straight drive (ramp up, cruise at 0.5 m/s, ramp down) sampled at several rates, the
joint positions in whole counts of several resolutions, the velocities the true wheel speed:
each row gives the distance the odometer (the node's and ``skidkin predict``'s code) reads under
``position`` and ``auto``. Run it on two trees to compare them::

    python -m lab.bench.encoder_bench
"""

from __future__ import annotations

import math

import numpy as np
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.odometer import Odometer

RADIUS_M = 0.1651
CASES = ((1000, 4096), (100, 1024), (50, 100), (1000, 100), (100, 100), (1000, 1024))


def encoder_drive(rate_hz: int, counts: int) -> list[tuple[int, float, float]]:
    """Return (t_ns, omega rad/s, position rad) of the drive, the position in whole counts."""
    quantum = 2 * math.pi / counts
    omega_max = 0.5 / RADIUS_M
    ramp_s = 0.2
    cruise_s = 0.5 / RADIUS_M / omega_max - ramp_s
    t = np.arange(int((2 * ramp_s + cruise_s + 0.5) * rate_hz)) / rate_hz
    omega = omega_max * np.clip(np.minimum(t / ramp_s, (2 * ramp_s + cruise_s - t) / ramp_s),
                                0.0, 1.0)
    theta = np.concatenate([[0.0], np.cumsum(0.5 * (omega[1:] + omega[:-1]) / rate_hz)])
    position = np.floor(theta / quantum + 1e-9) * quantum + 1.234
    return [(10**12 + int(round(a * 1e9)), float(w), float(p))
            for a, w, p in zip(t, omega, position)]


def distance_m(signal: str, drive: list[tuple[int, float, float]]) -> float:
    """Return the distance the odometer reads under ``signal``."""
    odometer = Odometer.from_config(OdometryConfig.from_flat({'wheel_signal': signal}))
    for t_ns, omega, position in drive:
        odometer.joint_sample(t_ns, omega, omega, t_ns, ((position,), (position,)))
    return math.hypot(*odometer.pose[:2])


def main() -> None:
    for rate_hz, counts in CASES:
        drive = encoder_drive(rate_hz, counts)
        print(f'{rate_hz:5d} Hz {counts:5d} counts/turn: position '
              f'{distance_m("position", drive):.4f} m, auto {distance_m("auto", drive):.4f} m '
              '(true 0.5000 m)')


if __name__ == '__main__':
    main()
