"""IMU-aided odometry: the gyro's yaw rate beside the kinematic model.

Three pieces, used by :class:`~skidkin_ros.core.odometry.odometer.Odometer`, so the node and
``skidkin predict`` run the same code (the buffer and its batch twins live in
:mod:`~skidkin_ros.core.odometry.gyro_buffer`, the filter in
:mod:`~skidkin_ros.core.odometry.gyro_filter`, the parameters in
:mod:`~skidkin_ros.core.odometry.gyro_params`; this module is the aid and re-exports them):

* :class:`GyroBuffer` keeps the recent gyro samples (NaN/inf, older and duplicate stamps are
  counted and not kept; saturated ones are kept as holes; a lone sample further than
  ``imu.spike`` from both neighbours, on the same side, is a glitch and skipped; a stamp more
  than ``max_stamp_step_back`` behind the newest, confirmed by ``STEP_BACK_CONFIRM`` such
  samples in a row, is the IMU driver's clock stepping back (a restart): the history is
  dropped and the gyro is used again from its new clock, never locked out until the new clock
  passes the old one) and answers
  one question,
  :meth:`GyroBuffer.mean_rate`: the corrected mean yaw rate over a wheel interval [t0, t1], or why
  there is none. The interval is whatever the integrator integrates (its wheel convention picks
  the speeds, the gyro is averaged over exactly the same span), shifted by the time offset.
* :class:`GainBiasFilter`: a 2-state Kalman filter on the model's yaw-rate gain ``gamma`` (1 on
  the calibration ground) and the gyro's residual bias ``beta``; measurement
  ``z = gamma w_mid + beta`` with ``w_mid`` the model's yaw rate at the interval's midpoint.
* :class:`GyroAid` applies the mode to each integrated interval: ``fuse`` integrates the gyro's
  bias-corrected yaw rate (the model's translation), ``adapt`` the model's yaw rate times the
  learned gain; an interval without gyro falls back to the learned gain in both. A gyro that
  contradicts the wheels beyond what any skid allows (mounted z-down: the other way round;
  read in deg/s: 57 times too fast) is not used: :class:`GyroCheck` compares the gyro's turn
  with the model's over every ``CHECK_TURN_RAD`` of the model's turning; while the ratio lies
  outside ``PLAUSIBLE_RATIO`` (a skid turns the robot less than the model says, never the
  other way, never several times more) both modes run the calibrated model (gain 1) and say
  so; a later window that agrees takes the gyro back.

The offline tools that read a recorded gyro (the gyro calibration, the ground-truth guard) take
it under the same rules in batch: :func:`usable_gyro` (the buffer's sample rules) and
:class:`GyroIntegral` (its piecewise-linear integral and which intervals it covers), checked
against :meth:`GyroBuffer.mean_rate` in ``test_gyro.py``.

Gyro measurement model (``imu.scale``, ``imu.bias``, ``imu.time_offset``)::

    g(t_stamp) = scale * omega(t_stamp - time_offset) + bias + noise

so the body's yaw rate at wheel time t is (g(t + time_offset) - bias) / scale. time_offset > 0:
the gyro's stamps are late with respect to the wheel clock (the Husky's: -0.172 s, early).
"""

from __future__ import annotations

import collections
from dataclasses import dataclass
import math
from typing import Callable

from skidkin_ros.core.odometry.gyro_buffer import GyroBuffer, GyroIntegral, usable_gyro
from skidkin_ros.core.odometry.gyro_filter import GainBiasFilter
from skidkin_ros.core.odometry.gyro_params import (GYRO_MODES, GYRO_RATE_LIMIT, GYRO_SPECS,
                                                   GyroParams, GyroStatus, STEP_BACK_CONFIRM)
from skidkin_ros.core.timeunits import NS_PER_S

# The names this module has always exported; the sample rules, the filter and the parameters
# live in gyro_buffer, gyro_filter and gyro_params.
__all__ = ['GYRO_MODES', 'GYRO_SPECS', 'GYRO_RATE_LIMIT', 'STEP_BACK_CONFIRM', 'GyroCheck',
           'CHECK_TURN_RAD', 'PLAUSIBLE_RATIO', 'GyroParams', 'GyroStatus', 'GyroBuffer',
           'GainBiasFilter', 'usable_gyro', 'GyroIntegral',
           'GyroAid', 'AidStep']

# The gyro is checked against the model over windows of this much model turning (rad), from
# intervals where the model turns faster than CHECK_MIN_RATE (rad/s; slower, a small bias
# would decide). The gyro's turn over the model's (signed): a skid turns the robot less than
# the model says (a calibrated model: about as much), so a ratio outside this range is a gyro
# mounted the other way round (about -1) or read in the wrong unit (57 for deg/s).
CHECK_TURN_RAD = 0.3
CHECK_MIN_RATE = 0.05
PLAUSIBLE_RATIO = (-0.3, 3.0)


class GyroCheck:
    """Tell whether the gyro turns the way the wheels say, by a plausible amount.

    ``add(gyro_rate, model_rate, dt_s)`` per covered interval in motion; returns a message when
    the verdict changes (``contradicts`` says the current one; the first window decides).
    """

    def __init__(self) -> None:
        self.contradicts = False
        self.ratio = math.nan   # of the last complete window
        self._gyro = 0.0
        self._model = 0.0

    def add(self, gyro_rate: float, model_rate: float, dt_s: float) -> str:
        if not abs(model_rate) > CHECK_MIN_RATE:
            return ''
        sign = 1.0 if model_rate > 0.0 else -1.0
        self._gyro += sign * gyro_rate * dt_s
        self._model += abs(model_rate) * dt_s
        if self._model < CHECK_TURN_RAD:
            return ''
        ratio = self._gyro / self._model
        self.ratio = ratio
        self._gyro = self._model = 0.0
        low, high = PLAUSIBLE_RATIO
        contradicts = not low <= ratio <= high
        if contradicts == self.contradicts:
            return ''
        self.contradicts = contradicts
        if contradicts:
            hint = ('the other way round: mounted upside down (z down) or the wrong frame?'
                    if ratio < 0 else 'far faster: a rate in deg/s, or a wrong imu.scale?')
            return (f'the gyro contradicts the wheels beyond any skid: over the last '
                    f'{CHECK_TURN_RAD:g} rad of turning it turned {ratio:.3g} times what the '
                    f'model says (a skid allows {low:g} to {high:g}), {hint} The gyro is not '
                    'used: the odometry runs the calibrated model until the gyro agrees again')
        return (f'the gyro agrees with the wheels again (it turned {ratio:.3g} times what the '
                'model says over the last window): the gyro is used again')


@dataclass
class AidStep:
    """What the aid did to the last integrated interval (for the covariance and diagnostics)."""

    status: GyroStatus = GyroStatus.STALE
    yaw_from_gyro: bool = False
    model_yaw_rate: float = 0.0
    dt_s: float = 0.0


class GyroAid:
    """Fuse or adapt one integrated interval at a time (the integrator's ``aid`` hook).

    Call it with the interval [t0, t1] the integrator integrates, the twist it would integrate
    (chosen by its wheel convention), the speeds at both ends and the twist source; it returns
    the twist to integrate instead. ``counts`` counts the intervals by :class:`GyroStatus` (gyro
    samples are counted by the buffer).
    """

    def __init__(self, params: GyroParams, wheel_radius_m: float) -> None:
        if params.mode == 'off':
            raise ValueError('GyroAid needs imu.mode adapt or fuse')
        self.params = params
        self.wheel_radius_m = float(wheel_radius_m)
        self.buffer = GyroBuffer(params)
        self.filter = GainBiasFilter(params)
        self.counts: collections.Counter[str] = collections.Counter()
        self.last = AidStep()
        self.check = GyroCheck()
        self._ahead_said = False
        self.news = ''   # what the check last said, for the odometer to report (then cleared)
        self.last_usable_ns: int | None = None
        # the heading error a constant residual bias leaves builds up over all fused intervals
        # (beta * T, not a sum of independent beta * dt): its standard deviation so far (rad;
        # back to 0 with the pose's covariance) and the variance the last interval added
        self.bias_yaw_sd = 0.0
        self._bias_step_var = 0.0
        # calibration: a list to collect (gyro rate - learned bias, w_mid) of every covered
        # interval in motion, the filter's measurement and its model (None: not collected)
        self.record: list[tuple[float, float]] | None = None

    def __call__(self, t0_ns: int, t1_ns: int, dt_s: float,
                 twist: tuple[float, float, float], speeds0: tuple[float, float],
                 speeds1: tuple[float, float], rate_of: Callable[[float, float], float] | None
                 ) -> tuple[float, float, float]:
        p = self.params
        vx, vy, w_model = twist
        l0, r0 = speeds0
        l1, r1 = speeds1
        if rate_of is None:     # a stateful source: its twist is already the interval mean
            w_mid = w_model
        else:
            w_mid = 0.5 * (rate_of(l0, r0) + rate_of(l1, r1))
        travel = 0.25 * self.wheel_radius_m * (abs(l0) + abs(r0) + abs(l1) + abs(r1)) * dt_s
        moving = max(abs(l0), abs(r0), abs(l1), abs(r1)) >= p.standstill
        status, rate = self.buffer.mean_rate(t0_ns, t1_ns)
        if status is GyroStatus.NO_HISTORY:
            status = self._no_history(t1_ns)
        elif status is GyroStatus.COVERED:
            self._ahead_said = False
        kf = self.filter
        kf.predict(travel, dt_s, status is GyroStatus.STALE)
        covered = status is GyroStatus.COVERED
        if covered and moving:
            news = self.check.add(rate - kf.bias, w_model, dt_s)
            if news:
                self.news = news
                kf.reset()   # a gain learned from that gyro means nothing
        if covered and self.check.contradicts:
            status, covered = GyroStatus.CONTRADICTS, False
        self.counts[status.value] += 1
        if covered:
            if self.record is not None and moving:
                self.record.append((rate - kf.bias, w_mid))
            kf.update(rate, w_mid, moving, dt_s)
        from_gyro = p.mode == 'fuse' and covered
        if from_gyro:
            w = rate - kf.bias if moving else 0.0
        elif status is GyroStatus.CONTRADICTS:
            w = w_model   # the calibrated model: the gyro is not used at all
        else:
            w = kf.gain * w_model
        self._bias_step_var = 0.0
        if from_gyro and moving:
            before = self.bias_yaw_sd
            self.bias_yaw_sd = before + math.sqrt(max(kf.p11, 0.0)) * dt_s
            self._bias_step_var = self.bias_yaw_sd ** 2 - before ** 2
        self.last = AidStep(status, from_gyro, w_model, dt_s)
        return vx, vy, w

    def _no_history(self, t1_ns: int) -> GyroStatus:
        """Tell a gyro whose whole history lies far after the interval (its clock is ahead).

        After the wheels' clock stepped back (their driver restarted, the IMU's did not) every
        gyro sample is later than every wheel interval: said once, not used until they agree.
        """
        buffer = self.buffer
        oldest = buffer.oldest_ns
        ahead_ns = (oldest - (t1_ns + buffer._offset_ns())) if oldest is not None else 0
        if ahead_ns <= buffer.max_step_back_ns:
            return GyroStatus.NO_HISTORY
        if not self._ahead_said:
            self._ahead_said = True
            self.news = (f'the gyro stamps are {ahead_ns / NS_PER_S:.3f} s ahead of the wheel '
                         'stamps (one driver restarted on another clock?): the gyro is not used '
                         'until the clocks agree')
        return GyroStatus.CLOCK_AHEAD

    def yaw_step_variance(self, model_variance: float) -> float:
        """Variance of the last interval's heading increment (rad^2), by where it came from.

        fuse on the gyro: white noise arw^2 dt plus what the residual bias adds in motion,
        (s + sqrt(P_beta) dt)^2 - s^2 with s the bias's heading error so far (the bias is one
        error over all intervals: after T s of fused motion its heading variance is P_beta T^2,
        not P_beta T dt); otherwise the model's variance scaled by gain^2 (and by
        imu.adapt.yaw_noise_scale in adapt: the share of the model's heading noise the gain
        leaves) plus the gain's (w_model dt)^2 P_gamma. (The heading's variance is right; its
        correlation from interval to interval, and so the position's share, is not carried: a
        straight drive's lateral variance from the bias is about 2/3 of the true one.)
        """
        last, kf = self.last, self.filter
        dt = last.dt_s
        if last.yaw_from_gyro:
            return self.params.arw ** 2 * dt + self._bias_step_var
        return (kf.gain ** 2 * self._model_share() * model_variance
                + (last.model_yaw_rate * dt) ** 2 * kf.p00)

    def _model_share(self) -> float:
        """Return the model's yaw variance factor: yaw_noise_scale in adapt, 1 in fuse."""
        return self.params.yaw_noise_scale if self.params.mode == 'adapt' else 1.0

    def yaw_rate_variance(self, model_variance: float, period_s: float,
                          model_yaw_rate: float) -> float:
        """Variance of the published yaw rate (rad^2/s^2) in the mode in force."""
        kf = self.filter
        if self.last.yaw_from_gyro:
            return self.params.arw ** 2 / max(period_s, 1e-9) + kf.p11
        return (kf.gain ** 2 * self._model_share() * model_variance
                + model_yaw_rate ** 2 * kf.p00)

    def state(self) -> dict[str, float]:
        """Return the filter's state for /diagnostics and reports."""
        kf = self.filter
        return {'gain': kf.gain, 'gain_sigma': math.sqrt(max(kf.p00, 0.0)), 'bias': kf.bias,
                'bias_sigma': math.sqrt(max(kf.p11, 0.0)), 'updates': float(kf.updates),
                'inflated': float(kf.inflated),
                'contradicts_wheels': float(self.check.contradicts),
                'turn_ratio': self.check.ratio}
