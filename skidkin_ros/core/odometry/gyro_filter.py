"""The gyro's gain/bias filter.

A 2-state Kalman filter on the model's yaw-rate gain and the gyro's residual bias (see
:mod:`~skidkin_ros.core.odometry.gyro` for how the aid uses it).
"""

from __future__ import annotations

import math

from skidkin_ros.core.odometry.gyro_params import GyroParams

__all__ = ['GainBiasFilter']


class GainBiasFilter:
    """Kalman filter on [gamma, beta]: the model's yaw-rate gain and the residual gyro bias.

    Plain floats (2 x 2, symmetric: p00, p01, p11). ``predict`` adds the random walks (gain per
    metre of wheel travel, bias per second) and, for a stale gyro, relaxes the gain toward 1 over
    ``fallback_distance`` with its variance growing back toward the prior. ``update`` takes one
    covered interval: moving, z = gamma w_mid + beta (only gamma is corrected; R = r_floor +
    (r_rel w_mid)^2); at standstill z = beta (the bias is learned; R = arw^2 / dt).
    Huber-inflated R (an innovation beyond k sigma counts as k sigma), Joseph form, gamma
    clamped to [gain_min, gain_max].
    """

    def __init__(self, params: GyroParams) -> None:
        self.params = params
        self.reset()

    def reset(self) -> None:
        """Back to the calibrated model: gain 1, bias 0, the prior covariance."""
        p = self.params
        self.gain = 1.0
        self.bias = 0.0
        self.p00 = p.gain_sigma ** 2
        self.p01 = 0.0
        self.p11 = p.bias_sigma ** 2
        self.inflated = 0
        self.updates = 0
        self.at_bound = False

    def predict(self, travel_m: float, dt_s: float, stale: bool) -> None:
        p = self.params
        q_gain = p.q_gain * travel_m
        if stale:
            decay = math.exp(-travel_m / p.fallback_distance)
            self.gain = 1.0 + (self.gain - 1.0) * decay
            self.p00 *= decay * decay
            self.p01 *= decay
            q_gain += p.gain_sigma ** 2 * (1.0 - decay * decay)
        self.p00 += q_gain
        self.p11 += p.q_bias * dt_s

    def update(self, z: float, w_mid: float, moving: bool, dt_s: float = 0.05) -> None:
        p = self.params
        if moving:
            h0, h1 = w_mid, 0.0
            r = p.r_floor + (p.r_rel * w_mid) ** 2
        else:   # at rest the model is exact (0): only the gyro's white noise over dt remains
            h0, h1 = 0.0, 1.0
            r = p.arw * p.arw / max(dt_s, 1e-3) + 1e-10
        nu = z - (self.gain * w_mid + self.bias)
        ph0 = self.p00 * h0 + self.p01 * h1
        ph1 = self.p01 * h0 + self.p11 * h1
        hph = h0 * ph0 + h1 * ph1
        s = hph + r
        k2 = p.huber_k * p.huber_k
        if nu * nu > k2 * s:
            r = nu * nu / k2 - hph
            s = nu * nu / k2
            self.inflated += 1
        # Moving, H = [w_mid, 0] and the gain and bias errors stay uncorrelated (no update ever
        # mixes them), so k1 = 0: the bias is learned at standstill only.
        k0, k1 = ph0 / s, ph1 / s
        # Joseph form: P = (I - K H) P (I - K H)^T + R K K^T
        a00, a01 = 1.0 - k0 * h0, -k0 * h1
        a10, a11 = -k1 * h0, 1.0 - k1 * h1
        b00 = a00 * self.p00 + a01 * self.p01
        b01 = a00 * self.p01 + a01 * self.p11
        b10 = a10 * self.p00 + a11 * self.p01
        b11 = a10 * self.p01 + a11 * self.p11
        self.p00 = b00 * a00 + b01 * a01 + r * k0 * k0
        self.p01 = b00 * a10 + b01 * a11 + r * k0 * k1
        self.p11 = b10 * a10 + b11 * a11 + r * k1 * k1
        gain = self.gain + k0 * nu
        self.bias += k1 * nu
        self.at_bound = not p.gain_min < gain < p.gain_max
        self.gain = min(max(gain, p.gain_min), p.gain_max)
        self.updates += 1
