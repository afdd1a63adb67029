"""The gyro's sample rules: the live buffer and its batch twins.

:class:`GyroBuffer` keeps the recent gyro samples and answers :meth:`GyroBuffer.mean_rate`, the
corrected mean yaw rate over a wheel interval or why there is none; :func:`usable_gyro` (the
buffer's sample rules) and :class:`GyroIntegral` (its piecewise-linear integral and which
intervals it covers) take a recorded gyro under the same rules in batch for the offline tools.
The rules and the measurement model are described in :mod:`~skidkin_ros.core.odometry.gyro`.
"""

from __future__ import annotations

import bisect
import collections
import math

import numpy as np

from skidkin_ros.core.odometry.gyro_params import GyroParams, GyroStatus, STEP_BACK_CONFIRM
from skidkin_ros.core.timeunits import NS_PER_S, s_to_ns

__all__ = ['GyroBuffer', 'usable_gyro', 'GyroIntegral']


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
