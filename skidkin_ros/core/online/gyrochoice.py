"""Online calibration while holding: the gyro weighs the remembered grounds.

While the reference is missing and the grounds alternate (``holding.py``: the grounds' Markov
blend), a gyro in use (``imu.mode`` fuse or adapt) tells which ground explains the wheels'
turning: the grounds differ in yaw slip, so each predicts another yaw rate from the same wheel
speeds. Every look at the blend (``HOLD_CHECK_S`` of wheel time), the yaw each ground's
parameters give over the wheel steps since the last look is compared with the gyro's yaw over
the same interval, and the blend's weights are those of a hidden Markov model's forward filter:
the chain of ``holding.py`` carries the weights from one look to the next (``p = pi + (p - pi)
exp(-mu d)`` over the d metres between them), then each is multiplied by its ground's
likelihood, a normal density of the yaw difference with the variance of

* the gyro's white noise and residual bias over the interval (``imu.arw``, ``imu.bias_sigma``),
* the wheels' yaw-rate noise (``WHEEL_Q``: encoder noise; the file's noise rates are those of
  metres-long segments, far too wide over a tenth of a second),
* the right ground's own error, ``RELATIVE`` of the yaw (its parameters, unmodelled slip),

times ``TEMPER`` (the looks are not independent: the same wheel noise and unmodelled slip reach
consecutive looks). Driving straight, every ground predicts the same yaw: the likelihoods are
equal and the weights are the chain's. Without a gyro (or with one that does not cover the
interval: stopped, stale) the chain alone goes on, and until the gyro has said anything in this
hold the weights are bit for bit those of ``holding.py``. The published covariance is the
mixture's with these weights.
"""

from __future__ import annotations

import bisect
import math

import numpy as np

from skidkin_ros.core.online.steps import LEFT, RIGHT, T0

__all__ = ['GyroChoice', 'TEMPER']

# The likelihood's variance is inflated by this (consecutive looks share wheel noise and slip).
TEMPER = 2.0
# The right ground's yaw error, relative to the yaw (its parameters' error, unmodelled slip).
RELATIVE = 0.03
# White noise of the wheels' yaw rate, (rad/s)^2 s (encoder noise at a few tens of Hz).
WHEEL_Q = 2e-5


class GyroChoice:
    """The gyro's weighing of the grounds while holding (a mixin of the calibrator)."""

    # (plan, weights, travel at the last look, wheel time of the last look, gyro heard)
    _gyro_hold: tuple | None = None

    def _gyro_weigh(self, t1_ns: int, plan: tuple, travel: float,
                    weights: np.ndarray) -> np.ndarray:
        """Return the blend's weights at t1_ns: ``weights`` (the chain's) until the gyro speaks."""
        grounds, pi, mu = plan
        state = self._gyro_hold
        if state is None or state[0] is not plan:
            self._gyro_hold = (plan, weights, travel, t1_ns, False)
            return weights
        _, p, at, since_ns, heard = state
        p = pi + (p - pi) * math.exp(-mu * max(travel - at, 0.0))
        turn = (self.gyro_turn(since_ns, t1_ns) if self.gyro_turn is not None
                and not hasattr(self.model, 'layout') else None)
        yaws = self._ground_yaws(grounds, since_ns, t1_ns) if turn is not None else None
        if yaws is None or not math.isfinite(turn):
            self._gyro_hold = (plan, p if heard else weights, travel, t1_ns, heard)
            return p if heard else weights
        dt_s = (t1_ns - since_ns) * 1e-9
        arw, bias = self.gyro_noise
        var = TEMPER * (arw ** 2 * dt_s + (bias * dt_s) ** 2 + WHEEL_Q * dt_s
                        + (RELATIVE * turn) ** 2 + 1e-12)
        log_l = -0.5 * (yaws - turn) ** 2 / var
        p = p * np.exp(log_l - log_l.max())
        p = p / p.sum()
        self.counters['online_hold_gyro'] += 1
        self._gyro_hold = (plan, p, travel, t1_ns, True)
        return p

    def _ground_yaws(self, grounds: list, t_a: int, t_b: int) -> np.ndarray | None:
        """Return each ground's yaw (rad) over the wheel steps ending in (t_a, t_b], or None."""
        t1 = self._steps.t1
        i0 = bisect.bisect_right(t1, t_a)
        i1 = bisect.bisect_right(t1, t_b)
        if i1 <= i0:
            return None
        rows = self._steps.rows[i0:i1]
        left = np.array([r[LEFT] for r in rows])
        right = np.array([r[RIGHT] for r in rows])
        dt_s = (np.array(t1[i0:i1], dtype=np.int64)
                - np.array([r[T0] for r in rows], dtype=np.int64)) * 1e-9
        return np.array([float(self.model.twist(g.k, self.geometry, left, right)[:, 2] @ dt_s)
                         for g in grounds])
