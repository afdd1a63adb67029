"""The reference's delay, checked online with the offline lag rule.

``online.time_offset`` (the reference stamp minus the wheel stamp of the same motion) is taken
as given by the learner; a lidar odometry or a SLAM is typically 50-300 ms late, and a wrong
value makes every turn look like a change of ground. This check measures the delay while
driving, by :mod:`skidkin_ros.core.calibration.lag`'s rule (the one ``skidkin diagnose`` uses
on a recording):

* **Data, bounded**: the wheels' running travel and rotation (the learner's wheel steps,
  ``steps.py``, read once per judged reference pose: through the file's model when it is linear,
  so that what is learned under a wrong delay does not bias the measurement; else the model in
  force), kept every ``WHEEL_EVERY_S`` at most, and the accepted reference poses (already in
  wheel time: stamp minus the ``time_offset`` in force) of the last ``WINDOW_S`` seconds.
* **Cost at a lag**: over each interval between two accepted reference poses of one chain, the
  reference's speed and yaw rate against the wheels' over the same interval read ``lag``
  earlier (:func:`~skidkin_ros.core.calibration.lag.velocity_cost`; the lateral component is
  zero on both sides). Only intervals the wheels cover at every lag scanned are used.
* **When**: every ``CHECK_EVERY_S`` of reference time (not per wheel sample or per pose): a
  scan of ``RANGE_S`` each way is about 35 costs of a few hundred interpolated values; the wheel
  steps are read then and before the learner drops any.
* **Verdict**: the lag found is the error of the ``time_offset`` in force; the measured delay is
  that offset plus it. A verdict needs turning in the window (the reference's yaw rate varies by
  ``MIN_YAW_RATE_SD`` at least), a best lag inside the scan (not at its edge) and a sigma at
  most ``MAX_SIGMA_S``. A lag beyond the tolerance (by more than its sigma) is
  said once (WARN ``reference_delay``: the value to set) and, with ``online.delay_learn``
  (default), taken in force: the offset becomes the measured delay (10 ms steps, within -1 to
  1 s, at most ``MAX_CORRECTIONS`` times), the learner's buffers restart and its grounds go back
  to the file's parameters (what was learned under the wrong stamps is dropped), counted
  ``online_delay_corrected``; without it, learning pauses (each segment not learned counted
  ``online_reference_delay``, state ``holding``) until a verdict within the tolerance. Without
  a verdict the one in force stays. ``delay_tolerance`` 0: not checked, nothing measured.

Why learn it: a field roboticist expects not to lose a day of learning to a wrong constant, and
pausing keeps the robot on the ground it was on (on the simulator's drives with a change of
ground, pausing was worse than not checking at all). Where the configured value is right the
check never acts, so learning is unchanged bit for bit (the check only reads).
"""

from __future__ import annotations

import bisect
import collections
import math

import numpy as np

from skidkin_ros.core.calibration.lag import lag_sigma, LAG_STEP_S, scan, velocity_cost
from skidkin_ros.core.online.steps import CHAIN, LEFT, RIGHT, T0, TRAVEL, TURN

__all__ = ['DelayCheck', 'RANGE_S', 'WINDOW_S', 'CHECK_EVERY_S', 'MIN_YAW_RATE_SD']

# Lags scanned each way (s): time_offset's error, beyond the 50-300 ms of a lidar odometry.
RANGE_S = 0.6
# Seconds of reference poses the lag is measured over.
WINDOW_S = 30.0
# Reference time between two measurements.
CHECK_EVERY_S = 2.0
# Wheel samples kept at most this often (s): fine against the 10 ms lag step.
WHEEL_EVERY_S = 0.01
# Turning needed for a verdict: the standard deviation of the reference's yaw rate (rad/s).
MIN_YAW_RATE_SD = 0.05
# A verdict needs the lag's standard deviation at most this (s).
MAX_SIGMA_S = 0.06
# Intervals needed for a verdict.
MIN_INTERVALS = 50
# Corrections of time_offset at most (delay_learn): a delay that keeps moving is paused on.
MAX_CORRECTIONS = 3
_NS = 1_000_000_000


class DelayCheck:
    """The online check of a learner's reference delay (module docstring)."""

    def __init__(self, time_offset_s: float, tolerance_s: float, track_width: float,
                 counters, warn, learn: bool = False,
                 file_rows: np.ndarray | None = None) -> None:
        self.offset_s = time_offset_s
        # J of the file's model (3, 2) when it is linear: the wheels' motion the reference is
        # aligned with (what is learned under a wrong delay must not bias its measurement)
        self.file_rows = None if file_rows is None else np.asarray(file_rows, float)
        self._sums = (0.0, 0.0)
        self.tolerance_s = tolerance_s
        self.learn = learn
        self.corrections = 0
        # a time_offset the learner takes in force after the pose being judged (None: none)
        self.correction: float | None = None
        self.track_width = track_width
        self.counters = counters
        self._warn = warn
        self.measured_s = math.nan       # time_offset + the lag found (the last measurement)
        self.sigma_s = math.nan
        self.pausing = False
        # chunks of (end stamps, travel, turn) arrays, one per read of the learner's steps
        self._wheels: collections.deque[tuple[np.ndarray, ...]] = collections.deque()
        self._wheel_chain: int | None = None
        self._wheel_last_ns = -(1 << 62)
        self._refs: collections.deque[tuple[int, float, float]] = collections.deque()
        self._intervals: collections.deque[tuple[int, int, float, float]] = collections.deque()
        self._next_check_ns: int | None = None
        self._last_ref = None

    @property
    def enabled(self) -> bool:
        return self.tolerance_s > 0.0

    def forget(self) -> None:
        """Forget the data (the learner's buffers restarted); keep the verdict in force."""
        self._wheels.clear()
        self._wheel_chain = None
        self._wheel_last_ns = -(1 << 62)
        self._refs.clear()
        self._intervals.clear()
        self._last_ref = None

    def summary(self) -> dict[str, float | str]:
        """Return what /diagnostics adds: the measured delay, its sigma and the verdict."""
        verdict = ('off' if not self.enabled else 'paused' if self.pausing
                   else 'unknown' if math.isnan(self.measured_s) else 'ok')
        return {'measured_delay': self.measured_s, 'measured_delay.sigma': self.sigma_s,
                'delay_check': verdict}

    def seen(self, refs, t1: list[int], rows: list) -> None:
        """Take the newest accepted reference pose of the learner's deque, once (gates.py).

        ``t1``, ``rows``: the learner's wheel steps (steps.py), read when a measurement is due
        (and before the learner drops any: :meth:`wheels`).
        """
        if not self.enabled or not refs or refs[-1] is self._last_ref:
            return
        ref = self._last_ref = refs[-1]
        # a chain starts with one pose (gates.py: _start_chain); later accepts keep two or more
        if self.reference(ref.t_ns, ref.path_m, ref.yaw, len(refs) == 1):
            self.wheels(t1, rows)
            self.measure()

    def wheels(self, t1: list[int], rows: list) -> None:
        """Keep the wheel steps not read yet (the learner's lists, steps.py).

        Called when a measurement is due and before the learner drops steps (calibrator.py:
        ``_trim``), not per reference pose: a few hundred steps at a time at 1 kHz.
        """
        if not self.enabled:
            return
        i = bisect.bisect_right(t1, self._wheel_last_ns)
        if i >= len(t1):
            return
        self._wheel_last_ns = t1[-1]
        kept = self._wheels
        cols = list(zip(*rows[i:]))   # the steps' fields, transposed in one pass
        ends = np.array(t1[i:], dtype=np.int64)
        chains = np.array(cols[CHAIN], dtype=np.int64)
        if self.file_rows is None:   # a non-linear model: the learner's model in force
            travel = np.array(cols[TRAVEL], dtype=float)
            turn = np.array(cols[TURN], dtype=float)
        else:                        # the file's linear model: independent of what is learned
            left = np.array(cols[LEFT], dtype=float)
            right = np.array(cols[RIGHT], dtype=float)
            dt_s = (ends - np.array(cols[T0], dtype=np.int64)) * 1e-9
            m = self.file_rows
            travel = self._sums[0] + np.cumsum(np.abs(m[0, 0] * left + m[0, 1] * right) * dt_s)
            turn = self._sums[1] + np.cumsum((m[2, 0] * left + m[2, 1] * right) * dt_s)
            self._sums = (float(travel[-1]), float(turn[-1]))
        cut = np.flatnonzero(chains != (chains[0] if self._wheel_chain is None
                                        else self._wheel_chain))
        if cut.size:   # a wheel gap: nothing to read across it (the last chain's steps only)
            start = int(np.flatnonzero(chains != chains[-1])[-1]) + 1 if np.any(
                chains != chains[-1]) else 0
            self._wheel_chain = int(chains[-1])
            kept.clear()
            ends, travel, turn = ends[start:], travel[start:], turn[start:]
        elif self._wheel_chain is None:
            self._wheel_chain = int(chains[0])
        # one value per WHEEL_EVERY_S (and the last): the lag step is 10 ms
        slot = ends // int(WHEEL_EVERY_S * _NS)
        pick = np.flatnonzero(np.diff(slot, append=slot[-1] + 1))
        kept.append((ends[pick], travel[pick], turn[pick]))
        horizon = int((WINDOW_S + 2.0 * RANGE_S + 1.0) * _NS)
        while len(kept) > 1 and kept[0][0][-1] < ends[-1] - horizon:
            kept.popleft()

    def reference(self, t_ns: int, path_m: float, yaw: float, new_chain: bool) -> bool:
        """Take one accepted reference pose (wheel time); True: a measurement is due."""
        if new_chain or not self._refs:
            self._refs.clear()
        elif t_ns > self._refs[-1][0]:
            a = self._refs[-1]
            self._intervals.append((a[0], t_ns, path_m - a[1], yaw - a[2]))
        self._refs.append((t_ns, path_m, yaw))
        if len(self._refs) > 2:
            self._refs.popleft()
        while self._intervals and self._intervals[0][0] < t_ns - WINDOW_S * _NS:
            self._intervals.popleft()
        if self._next_check_ns is None:
            self._next_check_ns = t_ns + int(CHECK_EVERY_S * _NS)
        elif t_ns >= self._next_check_ns:
            self._next_check_ns = t_ns + int(CHECK_EVERY_S * _NS)
            return True
        return False

    def measure(self) -> None:
        """Measure the lag over the window; update the verdict (module docstring)."""
        if not self._wheels or not self._intervals:
            return
        w = np.column_stack([np.concatenate(part) for part in zip(*self._wheels)])
        iv = np.array(self._intervals)
        t_a, t_b = iv[:, 0], iv[:, 1]
        reach = (RANGE_S + 0.01) * _NS
        ok = (t_a - reach >= w[0, 0]) & (t_b + reach <= w[-1, 0])
        if ok.sum() < MIN_INTERVALS:
            return
        t_a, t_b, dt_s = t_a[ok], t_b[ok], (t_b[ok] - t_a[ok]) * 1e-9
        v_ref, w_ref = iv[ok, 2] / dt_s, iv[ok, 3] / dt_s
        wt, travel, turn = w[:, 0] - w[0, 0], w[:, 1], w[:, 2]
        t_a, t_b = t_a - w[0, 0], t_b - w[0, 0]
        residual = np.zeros((v_ref.size, 3))

        def cost(lag: float) -> float:
            shift = lag * _NS
            a, b = t_a - shift, t_b - shift
            residual[:, 0] = v_ref - (np.interp(b, wt, travel) - np.interp(a, wt, travel)) / dt_s
            residual[:, 2] = w_ref - (np.interp(b, wt, turn) - np.interp(a, wt, turn)) / dt_s
            return velocity_cost(residual, self.track_width)

        lag, lags, curve = scan(cost, RANGE_S)
        sigma = lag_sigma(lags, curve, int(v_ref.size))
        self.measured_s, self.sigma_s = self.offset_s + lag, sigma
        if np.std(w_ref) < MIN_YAW_RATE_SD or abs(lag) >= RANGE_S - 2 * LAG_STEP_S:
            return   # too little turning, or the best lag at the scan's edge: no verdict
        if not sigma <= MAX_SIGMA_S:
            return
        if self.tolerance_s < abs(lag) <= self.tolerance_s + sigma:
            return   # beyond the tolerance, not clearly: the verdict in force stays
        off = abs(lag) > self.tolerance_s
        if off and self.learn and self.corrections < MAX_CORRECTIONS:
            new = min(max(round(self.measured_s / LAG_STEP_S) * LAG_STEP_S, -1.0), 1.0)
            self.corrections += 1
            self.counters['online_delay_corrected'] += 1
            self._warn('reference_delay', f'the reference is {self.measured_s * 1e3:+.0f} ms '
                       f'(+- {sigma * 1e3:.0f}) late against the wheels, online.time_offset '
                       f'was {self.offset_s * 1e3:+.0f} ms: {new:.2f} s taken in force, learning '
                       f'goes on; set online.time_offset: {new:.2f} in the file')
            self.correction, self.offset_s, self.pausing = new, new, False
            return
        if off and not self.pausing:
            self.counters['online_delay_warnings'] += 1
            self._warn('reference_delay', f'the reference is {self.measured_s * 1e3:+.0f} ms '
                       f'(+- {sigma * 1e3:.0f}) late against the wheels, online.time_offset '
                       f'is {self.offset_s * 1e3:+.0f} ms: learning paused; set '
                       f'online.time_offset: {self.measured_s:.2f}')
        self.pausing = off
