"""IMU-aided odometry: the gyro's yaw rate beside the kinematic model.

Three pieces, used by :class:`~skidkin_ros.core.odometry.odometer.Odometer`, so the node and
``skidkin predict`` run the same code:

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

import bisect
import collections
from dataclasses import dataclass, fields
import enum
import math
from typing import Any, Callable, Mapping

import numpy as np

from skidkin_ros.core.kinematics.specs import check_value, ParamSpec
from skidkin_ros.core.timeunits import NS_PER_S, s_to_ns

__all__ = ['GYRO_MODES', 'GYRO_SPECS', 'GYRO_RATE_LIMIT', 'STEP_BACK_CONFIRM', 'GyroCheck',
           'CHECK_TURN_RAD', 'PLAUSIBLE_RATIO', 'GyroParams', 'GyroStatus', 'GyroBuffer',
           'GainBiasFilter', 'usable_gyro', 'GyroIntegral',
           'GyroAid', 'AidStep']

GYRO_MODES = ('off', 'adapt', 'fuse')
# |yaw rate| no gyro measures (rad/s): the widest MEMS ranges are +-20 000 deg/s (349 rad/s).
# A recorded rate beyond it is a corrupt value, not a saturated sample.
GYRO_RATE_LIMIT = 400.0
# Samples in a row that confirm a stepped-back clock (one corrupt stamp is not a restart); the
# wheels' rule (the odometer imports it from here).
STEP_BACK_CONFIRM = 3
# The gyro is checked against the model over windows of this much model turning (rad), from
# intervals where the model turns faster than CHECK_MIN_RATE (rad/s; slower, a small bias
# would decide). The gyro's turn over the model's (signed): a skid turns the robot less than
# the model says (a calibrated model: about as much), so a ratio outside this range is a gyro
# mounted the other way round (about -1) or read in the wrong unit (57 for deg/s).
CHECK_TURN_RAD = 0.3
CHECK_MIN_RATE = 0.05
PLAUSIBLE_RATIO = (-0.3, 3.0)

# Node parameters imu.<name> (units in the descriptor, not the name; ranges as the node checks).
GYRO_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec('scale', '', 1.0, 0.5, 2.0,
              'gyro yaw-rate scale: g = scale * omega + bias (calibrated; a z-down IMU '
              'would be -1: fix the driver or the frame)'),
    ParamSpec('bias', 'rad/s', 0.0, -1.0, 1.0, 'gyro yaw-rate bias (calibrated)'),
    ParamSpec('time_offset', 's', 0.0, -1.0, 1.0,
              'gyro stamp minus the wheel stamp of the same motion (> 0: gyro stamps late; '
              'calibrated)'),
    ParamSpec('timeout', 's', 0.2, 0.0, 10.0,
              'no usable gyro sample this long before an interval end: gyro stale, the odometry '
              'goes on with the learned gain', lower_open=True),
    ParamSpec('max_gap', 's', 0.08, 0.0, 1.0,
              'longest gap between usable gyro samples inside an interval (a 20 Hz gyro needs '
              '0.06+)', lower_open=True),
    ParamSpec('max_wait', 's', 0.05, 0.0, 0.5,
              'node: longest wait of a wheel sample for the gyro samples that cover it'),
    ParamSpec('saturation', 'rad/s', 35.0, 0.0, 1e4,
              '|rate| at or above this is saturated (or absurd) and not used; set ~0.95 x the '
              'gyro range (default: 2000 deg/s, the largest usual MEMS range)', lower_open=True),
    ParamSpec('spike', 'rad/s', 0.5, 0.0, 1e4,
              'a sample this far from both its neighbours (a peak) is a glitch, skipped',
              lower_open=True),
    ParamSpec('arw', 'rad/sqrt(s)', 2e-3, 0.0, 1.0,
              'gyro white noise (angle random walk): the heading noise of fuse'),
    ParamSpec('bias_sigma', 'rad/s', 1e-3, 0.0, 1.0,
              'prior standard deviation of the residual gyro bias', lower_open=True),
    ParamSpec('q_bias', '(rad/s)^2/s', 1e-8, 0.0, 1.0, 'random walk of the gyro bias'),
    ParamSpec('adapt.q_gain', '1/m', 0.03, 0.0, 10.0,
              'random walk of the yaw-rate gain per metre of wheel travel'),
    ParamSpec('adapt.gain_sigma', '', 0.05, 0.0, 1.0,
              'prior standard deviation of the yaw-rate gain', lower_open=True),
    ParamSpec('adapt.r_floor', '(rad/s)^2', 0.033, 0.0, 100.0,
              'variance of gyro minus model yaw rate per interval, constant part',
              lower_open=True),
    ParamSpec('adapt.r_rel', '', 0.42, 0.0, 10.0,
              'relative part of that standard deviation (times the model yaw rate)'),
    ParamSpec('adapt.huber_k', '', 3.0, 1.0, 100.0,
              'innovations beyond this many sigma count as this many (a glitch cannot drag '
              'the gain)'),
    ParamSpec('adapt.gain_min', '', 0.5, 0.0, 1.0, 'lower bound of the yaw-rate gain',
              lower_open=True, upper_open=True),
    ParamSpec('adapt.gain_max', '', 1.5, 1.0, 100.0, 'upper bound of the yaw-rate gain',
              lower_open=True),
    ParamSpec('adapt.fallback_distance', 'm', 50.0, 0.0, 1e9,
              'gyro stale: the gain relaxes to 1 (the calibrated model) over this wheel travel',
              lower_open=True),
    ParamSpec('adapt.standstill', 'rad/s', 0.02, 0.0, 100.0,
              'both wheels slower than this: standstill (the bias is learned, fuse turns 0)'),
    ParamSpec('adapt.yaw_noise_scale', '', 1.0, 0.0, 100.0,
              "adapt: the model's yaw variance times this (the gyro removes part of the "
              "model's heading error; calibrated)"),
)
_ATTR = {spec.name: spec.name.replace('adapt.', '') for spec in GYRO_SPECS}


@dataclass(frozen=True)
class GyroParams:
    """The ``imu.*`` parameters (see ``GYRO_SPECS`` for units and meanings)."""

    mode: str = 'off'
    scale: float = 1.0
    bias: float = 0.0
    time_offset: float = 0.0
    timeout: float = 0.2
    max_gap: float = 0.08
    max_wait: float = 0.05
    saturation: float = 35.0
    spike: float = 0.5
    arw: float = 2e-3
    bias_sigma: float = 1e-3
    q_bias: float = 1e-8
    q_gain: float = 0.03
    gain_sigma: float = 0.05
    r_floor: float = 0.033
    r_rel: float = 0.42
    huber_k: float = 3.0
    gain_min: float = 0.5
    gain_max: float = 1.5
    fallback_distance: float = 50.0
    standstill: float = 0.02
    yaw_noise_scale: float = 1.0

    def __post_init__(self) -> None:
        if self.mode not in GYRO_MODES:
            raise ValueError(f'imu.mode must be one of {", ".join(GYRO_MODES)}, got {self.mode!r}')

    @classmethod
    def from_values(cls, values: Mapping[str, Any], prefix: str = 'imu.') -> 'GyroParams':
        """Return the parameters of a flat mapping (``imu.mode``, ``imu.scale``, ...), checked."""
        kwargs: dict[str, Any] = {'mode': values.get(prefix + 'mode', 'off')}
        for spec in GYRO_SPECS:
            if prefix + spec.name in values:
                kwargs[_ATTR[spec.name]] = check_value(spec, values[prefix + spec.name], prefix)
        return cls(**kwargs)

    def as_values(self, prefix: str = 'imu.') -> dict[str, Any]:
        """Return the flat ``imu.*`` mapping of these parameters (inverse of from_values)."""
        out: dict[str, Any] = {prefix + 'mode': self.mode}
        for spec in GYRO_SPECS:
            out[prefix + spec.name] = float(getattr(self, _ATTR[spec.name]))
        return out


assert {f.name for f in fields(GyroParams)} == set(_ATTR.values()) | {'mode'}


class GyroStatus(enum.Enum):
    """What happened to a gyro sample (first five), or why an interval has no gyro rate."""

    ACCEPTED = 'accepted'            # kept and usable
    NON_FINITE = 'non_finite'        # NaN or inf: not kept
    SATURATED = 'saturated'          # |rate| >= imu.saturation: kept as a hole
    OLDER = 'older'                  # stamp older than the newest kept: rejected
    CONTRADICTS = 'contradicts'      # interval: covered, but the gyro contradicts the wheels
    CLOCK_RESET = 'clock_reset'      # the gyro clock stepped back (confirmed): history dropped
    DUPLICATE = 'duplicate'          # same stamp as the newest kept: rejected
    COVERED = 'covered'              # interval: the mean rate is known
    NOT_YET = 'not_yet'              # interval end not (yet) bracketed by checked samples
    STALE = 'stale'                  # no usable sample within imu.timeout of the interval end
    GAP = 'gap'                      # a gap longer than imu.max_gap between usable samples
    SATURATED_INSIDE = 'saturated_inside'  # a saturated sample inside the interval
    NO_HISTORY = 'no_history'        # the interval starts before the oldest kept sample
    CLOCK_AHEAD = 'clock_ahead'      # ... by more than max_stamp_step_back: another clock


class GyroBuffer:
    """Recent gyro samples (about ``keep_s``) and the interval means the odometry asks for."""

    def __init__(self, params: GyroParams, keep_s: float = 3.0) -> None:
        self.params = params
        self._t: list[int] = []
        self._g: list[float] = []   # NaN marks a saturated sample (a hole)
        self._keep_ns = s_to_ns(keep_s)
        self.counts: collections.Counter[str] = collections.Counter()
        # A stamp further behind the newest than this (ns) may be a restarted clock (the
        # odometer sets it from max_stamp_step_back); the run of such stamps seen so far.
        self.max_step_back_ns = 3.0 * NS_PER_S
        self._back_run: list[tuple[int, float]] = []
        self.stepped_back_s = 0.0   # by how much the last confirmed step went back

    def clear(self) -> None:
        """Forget every sample (the clock jumped)."""
        self._t.clear()
        self._g.clear()
        self._back_run.clear()

    @property
    def newest_ns(self) -> int | None:
        return self._t[-1] if self._t else None

    @property
    def oldest_ns(self) -> int | None:
        return self._t[0] if self._t else None

    def _restarted(self, t_ns: int, rate: float) -> bool:
        """Take a stamp far behind the newest: True once a clock restart is confirmed.

        ``STEP_BACK_CONFIRM`` such stamps in a row, increasing and each within imu.timeout of
        the previous, confirm it (the wheels' rule, with the gyro's own spacing); the history is
        then dropped and the confirming samples are kept, on the new clock.
        """
        run = self._back_run
        if run and not 0 < t_ns - run[-1][0] <= self.params.timeout * NS_PER_S:
            run.clear()
        run.append((t_ns, rate))
        if len(run) < STEP_BACK_CONFIRM:
            return False
        self.stepped_back_s = (self._t[-1] - t_ns) / NS_PER_S
        kept = list(run)
        self.clear()
        for t_kept, rate_kept in kept:
            self._t.append(t_kept)
            self._g.append(rate_kept if abs(rate_kept) < self.params.saturation else math.nan)
        return True

    def add(self, t_ns: int, rate_rad_s: float) -> GyroStatus:
        """Keep one raw sample (stamp in ns on the gyro's clock); return what happened to it."""
        rate = float(rate_rad_s)
        t_ns = int(t_ns)
        if not math.isfinite(rate):
            status = GyroStatus.NON_FINITE
        elif self._t and t_ns < self._t[-1]:
            if (self._t[-1] - t_ns > self.max_step_back_ns
                    and self._restarted(t_ns, rate)):
                self.counts[GyroStatus.CLOCK_RESET.value] += 1
                return GyroStatus.CLOCK_RESET
            status = GyroStatus.OLDER
        elif self._t and t_ns == self._t[-1]:
            status = GyroStatus.DUPLICATE
        elif abs(rate) >= self.params.saturation:
            status = GyroStatus.SATURATED
        else:
            status = GyroStatus.ACCEPTED
        self.counts[status.value] += 1
        if status in (GyroStatus.ACCEPTED, GyroStatus.SATURATED):
            if self._back_run:
                self._back_run.clear()
            self._t.append(t_ns)
            self._g.append(rate if status is GyroStatus.ACCEPTED else math.nan)
            if len(self._t) > 64 and self._t[0] < t_ns - 2 * self._keep_ns:
                cut = bisect.bisect_left(self._t, t_ns - self._keep_ns)
                del self._t[:cut]
                del self._g[:cut]
        return status

    def _offset_ns(self) -> int:
        return s_to_ns(self.params.time_offset)

    def stale(self, t1_wheel_ns: int) -> bool:
        """Tell whether no sample is within imu.timeout before the (shifted) interval end."""
        newest = self.newest_ns
        return newest is None or (t1_wheel_ns + self._offset_ns() - newest
                                  > self.params.timeout * NS_PER_S)

    def ready(self, t1_wheel_ns: int) -> bool:
        """Tell whether an interval ending at t1 can be answered now: covered or stale.

        Covered needs a kept sample at or after t1 + offset and one more after it (so that one
        could be checked for a spike); the node waits up to imu.max_wait for them.
        """
        if self.stale(t1_wheel_ns):
            return True
        t = self._t
        end = t1_wheel_ns + self._offset_ns()
        return len(t) - bisect.bisect_left(t, end) >= 2

    def mean_rate(self, t0_wheel_ns: int, t1_wheel_ns: int) -> tuple[GyroStatus, float]:
        """Return (COVERED, corrected mean yaw rate rad/s) over the wheel interval, or why not.

        The interval is [t0 + offset, t1 + offset] on the gyro clock; the mean is the exact
        integral of the linear interpolation of the usable samples (trapezoids, including the
        partial pieces at both ends) divided by its length, then corrected:
        (mean - bias) / scale. This is the one place that matches gyro to wheels: any wheel
        convention (the speeds of the start, the end or both) integrates [t0, t1], and so does
        the gyro.
        """
        p = self.params
        off = self._offset_ns()
        t0, t1 = t0_wheel_ns + off, t1_wheel_ns + off
        t, g = self._t, self._g
        if self.stale(t1_wheel_ns):
            return GyroStatus.STALE, math.nan
        if t0 < t[0]:
            return GyroStatus.NO_HISTORY, math.nan
        i0 = bisect.bisect_right(t, t0) - 1          # last sample at or before t0
        i1 = bisect.bisect_left(t, t1)               # first sample at or after t1
        if i1 + 1 >= len(t):
            return GyroStatus.NOT_YET, math.nan
        lo, hi = max(i0 - 1, 0), min(i1 + 2, len(t))  # one neighbour on either side
        wt, wg = t[lo:hi], g[lo:hi]
        if any(math.isnan(v) for v in wg[i0 - lo:i1 - lo + 1]):
            return GyroStatus.SATURATED_INSIDE, math.nan
        ct: list[int] = []
        cg: list[float] = []
        last = len(wt) - 1
        for k, (tk, gk) in enumerate(zip(wt, wg)):
            if math.isnan(gk):
                continue
            if 0 < k < last:
                a, c = wg[k - 1], wg[k + 1]
                up, down = gk - a, gk - c
                if (up > p.spike and down > p.spike) or (up < -p.spike and down < -p.spike):
                    self.counts['spike'] += 1
                    continue
            ct.append(tk)
            cg.append(gk)
        j0 = bisect.bisect_right(ct, t0) - 1
        j1 = bisect.bisect_left(ct, t1)
        if j0 < 0:
            return GyroStatus.NO_HISTORY, math.nan
        if j1 >= len(ct):
            return GyroStatus.NOT_YET, math.nan
        gap_ns = p.max_gap * NS_PER_S
        for k in range(j0, j1):
            if ct[k + 1] - ct[k] > gap_ns:
                return GyroStatus.GAP, math.nan
        if t1 <= t0:
            mean = _value_at(ct, cg, j0, t0)
        else:
            mean = _integral(ct, cg, j0, j1, t0, t1) / (t1 - t0)
        return GyroStatus.COVERED, (mean - p.bias) / p.scale


def usable_gyro(t_ns: np.ndarray, rate: np.ndarray, params: GyroParams | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (t_ns, rate, holes) of a recorded gyro under :class:`GyroBuffer`'s sample rules.

    The batch form of :meth:`GyroBuffer.add` and the spike rule of :meth:`GyroBuffer.mean_rate`,
    for the offline tools (the gyro calibration, the ground-truth guard): non-finite samples and
    stamps not after the newest kept one are dropped; a sample further than imu.spike from both
    kept neighbours (on the same side; a saturated neighbour is never a reference) is dropped;
    a saturated sample is dropped and blocks every interval that reaches past the kept samples
    around it: ``holes`` (K, 2) holds those open spans (previous, next kept stamp).
    """
    p = params or GyroParams()
    t_ns = np.asarray(t_ns, dtype=np.int64)
    g = np.asarray(rate, dtype=float)
    keep = np.isfinite(g)
    t_ns, g = t_ns[keep], g[keep]
    if t_ns.size:
        newest = np.maximum.accumulate(t_ns)
        rising = np.concatenate([[True], t_ns[1:] > newest[:-1]])
        t_ns, g = t_ns[rising], g[rising]
    saturated = np.abs(g) >= p.saturation
    spike = np.zeros(g.size, dtype=bool)
    if g.size >= 3:
        up, down = g[1:-1] - g[:-2], g[1:-1] - g[2:]
        spike[1:-1] = (((up > p.spike) & (down > p.spike)) | ((up < -p.spike) & (down < -p.spike)))
        spike[1:-1] &= ~(saturated[:-2] | saturated[2:])
        spike &= ~saturated
    where = np.nonzero(saturated)[0]
    holes = np.stack([t_ns[np.maximum(where - 1, 0)],
                      t_ns[np.minimum(where + 1, t_ns.size - 1)]], axis=1)
    good = ~saturated & ~spike
    return t_ns[good], g[good], holes.reshape(-1, 2)


class GyroIntegral:
    """The integral of the linearly interpolated gyro, in batch (what ``mean_rate`` integrates).

    ``GyroIntegral(t_ns, rate).between(a_ns, b_ns)`` is the exact integral (rad) of the
    piecewise-linear rate over each [a, b] inside the samples, the same trapezoids as
    :meth:`GyroBuffer.mean_rate` (before its bias and scale correction); ``covered(a, b,
    max_gap_s, holes)`` tells which intervals inside the samples it answers: no gap longer
    than ``max_gap_s`` and no saturated sample's span (:func:`usable_gyro`) reached.
    """

    def __init__(self, t_ns: np.ndarray, rate: np.ndarray) -> None:
        self.t = np.asarray(t_ns, dtype=np.int64)
        self.g = np.asarray(rate, dtype=float)
        dt = np.diff(self.t) * 1e-9
        self.cumulative = np.concatenate([[0.0], np.cumsum(0.5 * (self.g[1:] + self.g[:-1]) * dt)])

    def at(self, t_ns: np.ndarray) -> np.ndarray:
        """Return the integral from the first sample up to each stamp (clipped to the samples)."""
        t, g = self.t, self.g
        at = np.clip(np.asarray(t_ns, dtype=np.int64), t[0], t[-1])
        i = np.clip(np.searchsorted(t, at, side='right') - 1, 0, t.size - 2)
        tau = (at - t[i]) * 1e-9
        slope = (g[i + 1] - g[i]) / ((t[i + 1] - t[i]) * 1e-9)
        return self.cumulative[i] + g[i] * tau + 0.5 * slope * tau * tau

    def between(self, a_ns: np.ndarray, b_ns: np.ndarray) -> np.ndarray:
        """Return the integral (rad) over each [a, b]."""
        return self.at(b_ns) - self.at(a_ns)

    def covered(self, a_ns: np.ndarray, b_ns: np.ndarray, max_gap_s: float,
                holes: np.ndarray | None = None) -> np.ndarray:
        """Tell which [a, b] lie inside the samples, with no long gap and no hole reached."""
        t = self.t
        a = np.asarray(a_ns, dtype=np.int64)
        b = np.asarray(b_ns, dtype=np.int64)
        inside = (a >= t[0]) & (b <= t[-1])
        long_gap = np.diff(t) > max_gap_s * NS_PER_S
        count = np.concatenate([[0], np.cumsum(long_gap)])
        i0 = np.clip(np.searchsorted(t, a, side='right') - 1, 0, t.size - 1)
        i1 = np.clip(np.searchsorted(t, b, side='left'), 0, t.size - 1)
        ok = inside & (count[i1] == count[i0])
        if holes is not None and len(holes):
            lo, hi = np.asarray(holes, dtype=np.int64).T      # both rise with the hole
            ok &= np.searchsorted(lo, b, side='left') <= np.searchsorted(hi, a, side='right')
        return ok


def _value_at(ts: list[int], gs: list[float], i: int, t: int) -> float:
    """Linear interpolation between samples i and i + 1 at t (ts[i] <= t <= ts[i + 1])."""
    if i + 1 >= len(ts) or t <= ts[i]:
        return gs[i]
    w = (t - ts[i]) / (ts[i + 1] - ts[i])
    return gs[i] + w * (gs[i + 1] - gs[i])


def _integral(ts: list[int], gs: list[float], j0: int, j1: int, t0: int, t1: int) -> float:
    """Return the integral (rad/s x ns) of the piecewise-linear signal over [t0, t1].

    Samples j0 and j1 bracket the interval: ts[j0] <= t0, ts[j1] >= t1.
    """
    total = 0.0
    a = t0
    value_a = _value_at(ts, gs, j0, t0)
    for k in range(j0, j1):
        b = ts[k + 1] if ts[k + 1] < t1 else t1
        if b > a:
            value_b = gs[k + 1] if b == ts[k + 1] else _value_at(ts, gs, k, b)
            total += 0.5 * (value_a + value_b) * (b - a)
            value_a = value_b
            a = b
    return total


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

        fuse on the gyro: white noise arw^2 dt plus the bias's P_beta dt^2; otherwise the model's
        variance scaled by gain^2 (and by imu.adapt.yaw_noise_scale in adapt: the share of the
        model's heading noise the gain leaves) plus the gain's (w_model dt)^2 P_gamma. (Per
        interval: the correlation of the gain and bias errors from interval to interval is not
        carried.)
        """
        last, kf = self.last, self.filter
        dt = last.dt_s
        if last.yaw_from_gyro:
            return self.params.arw ** 2 * dt + kf.p11 * dt * dt
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
