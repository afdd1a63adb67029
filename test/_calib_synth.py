"""Synthetic drives for the calibration tests: a known model driven by random wheel commands."""

from __future__ import annotations

import numpy as np

from skidkin_ros.core.drive import Drive, PoseTrack, WheelSamples
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.integrator import rollout
from skidkin_ros.core.odometry.interval import DEFAULT_INTERVAL, held_speeds

GEOMETRY = Geometry(0.1651, 0.555)

TRUE_VALUES = {
    'edd_symmetric': {'alpha': 0.9, 'b_hat': 1.04},
    'edd_asymmetric': {'alpha_l': 0.88, 'alpha_r': 0.93, 'x_v': -0.05, 'y_l': 0.5,
                       'y_r': -0.56},
    'roc': {'alpha': 0.9, 'beta_1': 1.5, 'beta_2': 0.4},
    'full_linear': {'gamma_11': 0.075, 'gamma_12': 0.079, 'gamma_21': -0.004,
                    'gamma_22': 0.005, 'gamma_31': -0.16, 'gamma_32': 0.15},
}


def wheel_commands(kind: str, n: int, rate_hz: float, rng: np.random.Generator,
                   hold_s: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Piecewise-constant wheel speeds (rad/s), smoothed by a first-order lag."""
    per = max(int(hold_s * rate_hz), 1)
    blocks = n // per + 1
    if kind == 'straight':
        speed = rng.uniform(1.0, 6.0, blocks) * rng.choice([-1.0, 1.0], blocks)
        left, right = speed, speed.copy()
    elif kind == 'spin':
        speed = rng.uniform(1.0, 6.0, blocks) * rng.choice([-1.0, 1.0], blocks)
        left, right = -speed, speed
    elif kind == 'rich':
        left = rng.uniform(-6.0, 6.0, blocks)
        right = rng.uniform(-6.0, 6.0, blocks)
    else:
        raise ValueError(kind)
    left = np.repeat(left, per)[:n]
    right = np.repeat(right, per)[:n]
    gain = 1.0 - np.exp(-1.0 / (0.3 * rate_hz))
    out_l = np.empty(n)
    out_r = np.empty(n)
    state = np.zeros(2)
    for i in range(n):
        state += gain * (np.array([left[i], right[i]]) - state)
        out_l[i], out_r[i] = state
    return out_l, out_r


def make_drive(model: str = 'edd_symmetric', values: dict | None = None, kind: str = 'rich',
               duration_s: float = 120.0, rate_hz: float = 50.0, truth_every: int = 5,
               wheel_noise: float = 0.0, truth_noise_m: float = 0.0,
               truth_noise_rad: float = 0.0, seed: int = 0, name: str = 'synth',
               geometry: Geometry = GEOMETRY, interval: str = DEFAULT_INTERVAL) -> Drive:
    """Drive the true model with random commands; truth is sub-sampled (and noisy if asked).

    The truth moves as the odometry does under ``interval`` (the default convention: sample k's
    speeds over [t_k-1, t_k]), so the true model predicts it exactly.
    """
    rng = np.random.default_rng(seed)
    n = int(duration_s * rate_hz) + 1
    t_ns = np.arange(n, dtype=np.int64) * int(round(1e9 / rate_hz))
    omega_l, omega_r = wheel_commands(kind, n, rate_hz, rng)
    values = TRUE_VALUES.get(model, {}) if values is None else values
    bound = get_model(model).bind(values, geometry)
    twist = bound.twist(held_speeds(omega_l, interval)[:-1], held_speeds(omega_r, interval)[:-1])
    poses = rollout(twist, np.diff(t_ns) * 1e-9)
    pick = np.arange(0, n, truth_every)
    noisy = poses[pick] + rng.normal(0.0, 1.0, (pick.size, 3)) * [
        truth_noise_m, truth_noise_m, truth_noise_rad]
    truth = PoseTrack(t_ns[pick], noisy[:, 0], noisy[:, 1], noisy[:, 2])
    wheels = WheelSamples(t_ns, omega_l + rng.normal(0.0, wheel_noise, n),
                          omega_r + rng.normal(0.0, wheel_noise, n))
    return Drive(name, wheels, truth, meta={'true_model': model})
