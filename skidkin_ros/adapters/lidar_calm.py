"""Where registrations start: seams and sample windows moved to where the wheels are calm.

A kiss-icp registration that starts from scratch has no motion for its first scan (deskewed as
if still) and builds its first map from a few scans. Started inside a fast spin in place, near
an abrupt change of the spin, that map is flawed: the registration misregisters the spin's
stop, its seam with the previous chunk is cut, and in a scene smaller than the lidar's range
the flaw stays in the map for the whole chunk (on the simulated forest, 120 s, seed 5: chunk
1 started at 56.1 s inside a 1.43 rad/s spin, erred by 100-220 mrad per frame at a later
reversal, and the self-check blamed the fast settings for it).

So every registration that starts from scratch after the recording's start starts where the
wheels say the robot turns least nearby:

* **A seam** (each chunk after the first): the warm-up [seam - overlap, seam) is placed, within
  a quarter chunk of the nominal seam (every ``chunk_s`` from the first cloud), where the mean
  of |omega_r - omega_l| (the wheels' turning, proportional to the yaw rate of a skid-steer
  robot; its scale does not matter, only where it is least) is least. The last chunk keeps at
  least a quarter chunk.
* **A self-check sample window** (:mod:`skidkin_ros.adapters.icp_selfcheck`): its warm-up is
  placed, up to one window length before where it would end (the end of a chunk), where the
  wheels turn least.

A place moves only where that halves the turning of its warm-up (so a recording calm at the
nominal seam, or turning alike everywhere, keeps today's cut, and encoder noise moves
nothing); ties go to the candidate nearest the nominal place (then the earlier). The rule reads the
recording only (its wheels, its lidar period, ``chunk_s`` and ``overlap_s``), never the number
of processes, so the poses stay the same for any ``--jobs``. Candidates are on a grid of one
lidar period. A candidate whose warm-up the wheels do not cover is not taken, and a nominal
place whose warm-up they do not cover stays (its turning is unknown); a recording without
wheels (or with fewer than two samples) keeps the nominal places. A gap in the wheel stamps
longer than ``_GAP_PERIODS`` median wheel periods and ``_GAP_MIN_S`` (a dropout, not jitter)
is not covered: a warm-up that overlaps it is unknown, not the last value held across it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.core.timeunits import s_to_ns

# A place moves only where its warm-up turns less than this share of the nominal one's: a
# recording that is calm at the nominal seam (or turns alike everywhere) keeps today's cut.
_MOVE_BELOW = 0.5
# A step between wheel stamps longer than both of these is a gap nobody measured.
_GAP_PERIODS = 10
_GAP_MIN_S = 0.5

__all__ = ['TurnSignal', 'calm_seams', 'calm_windows', 'nominal_seams', 'seams_placed_note',
           'turn_signal']


@dataclass(frozen=True)
class TurnSignal:
    """The wheels' turning |omega_r - omega_l| (rad/s), integrated: mean over any interval."""

    t_ns: np.ndarray
    integral: np.ndarray  # rad, at t_ns (the held value integrated from t_ns[0])
    gap_start_ns: np.ndarray  # the stamps before and after each gap (sorted)
    gap_stop_ns: np.ndarray

    def mean(self, start_ns: np.ndarray, stop_ns: np.ndarray) -> np.ndarray:
        """Return the mean turning over [start, stop) per interval; inf where not covered."""
        start = np.asarray(start_ns, dtype=np.int64)
        stop = np.asarray(stop_ns, dtype=np.int64)
        lo = np.interp((start - self.t_ns[0]) * 1e-9, self._t_s, self.integral)
        hi = np.interp((stop - self.t_ns[0]) * 1e-9, self._t_s, self.integral)
        span_s = np.maximum((stop - start) * 1e-9, 1e-9)
        gaps = (np.searchsorted(self.gap_start_ns, stop, 'left')
                - np.searchsorted(self.gap_stop_ns, start, 'right'))
        covered = (start >= self.t_ns[0]) & (stop <= self.t_ns[-1]) & (gaps == 0)
        return np.where(covered, (hi - lo) / span_s, np.inf)

    @property
    def _t_s(self) -> np.ndarray:
        return (self.t_ns - self.t_ns[0]) * 1e-9


def turn_signal(wheels: WheelSamples | None) -> TurnSignal | None:
    """Return the wheels' turning signal, or None without usable wheel samples."""
    if wheels is None or len(wheels) < 2:
        return None
    turn = np.abs(np.asarray(wheels.omega_r, dtype=float) - np.asarray(wheels.omega_l,
                                                                       dtype=float))
    ok = np.isfinite(turn)
    t_ns = np.asarray(wheels.t_ns, dtype=np.int64)[ok]
    turn = turn[ok]
    if t_ns.size < 2 or t_ns[-1] <= t_ns[0]:
        return None
    step_ns = np.diff(t_ns)
    integral = np.concatenate([[0.0], np.cumsum(turn[:-1] * step_ns * 1e-9)])
    gap = step_ns > max(_GAP_PERIODS * float(np.median(step_ns)), s_to_ns(_GAP_MIN_S))
    return TurnSignal(t_ns, integral, t_ns[:-1][gap], t_ns[1:][gap])


def nominal_seams(first_receive_ns: int, period_ns: int, n_frames: int,
                  chunk_ns: int) -> list[int]:
    """Return today's seams: every ``chunk_ns`` from the first cloud, the last chunk >= 1/4."""
    span_ns = max(int(n_frames), 1) * max(int(period_ns), 1)
    count = max(1, int(np.ceil(span_ns / chunk_ns - 0.25)))
    return [int(first_receive_ns) + k * int(chunk_ns) for k in range(1, count)]


def _calmest(signal: TurnSignal, nominal: int, low: int, high: int, span_ns: int,
             step_ns: int, before: bool) -> int:
    """Return the place in [low, high] (grid of step around nominal) whose span turns least.

    ``before``: the span is [place - span, place) (a seam's warm-up); else [place, place + span).
    """
    if high < low:
        return nominal
    k_low = -((nominal - low) // step_ns)
    k_high = (high - nominal) // step_ns
    shifts = np.arange(k_low, k_high + 1, dtype=np.int64)
    # nearest the nominal place first, the earlier of two equally near: argmin keeps the first
    shifts = shifts[np.lexsort((shifts, np.abs(shifts)))]
    places = nominal + shifts * step_ns
    starts = places - span_ns if before else places
    cost = signal.mean(starts, starts + span_ns)
    best = int(np.argmin(cost))
    # shifts[0] is the nominal place: it stays unless the best turns less than half as much
    # (and where the wheels miss its warm-up, how much it turns is unknown: it stays)
    if not np.isfinite(cost[0]) or not cost[best] < _MOVE_BELOW * cost[0]:
        return nominal
    return int(places[best])


def calm_seams(nominal: Sequence[int], wheels: WheelSamples | None, overlap_ns: int,
               chunk_ns: int, period_ns: int, end_ns: int) -> list[int]:
    """Return the seams moved to where the wheels turn least over each warm-up (module doc).

    ``nominal``: today's seams; ``end_ns``: an estimate of the last lidar receive time. Without
    wheels, the nominal seams.
    """
    signal = turn_signal(wheels)
    seams = [int(s) for s in nominal]
    if signal is None or not seams:
        return seams
    reach = int(chunk_ns) // 4
    step = max(int(period_ns), 10_000_000)
    out = []
    for k, seam in enumerate(seams):
        high = seam + reach
        if k == len(seams) - 1:
            high = max(min(high, int(end_ns) - reach), seam)
        out.append(_calmest(signal, seam, seam - reach, high, int(overlap_ns), step, True))
    return out


def calm_windows(windows: Sequence[tuple[int, int | None]], wheels: WheelSamples | None,
                 length_ns: int, warmup_ns: int, period_ns: int, first_ns: int
                 ) -> list[tuple[int, int | None]]:
    """Return sample windows moved up to one length earlier, to a calm warm-up (module doc).

    ``length_ns``: a window's length (warm-up included); a window that moves keeps it and gets
    a closed end (an open last window: ``start + length_ns``). Without wheels, unchanged.
    """
    signal = turn_signal(wheels)
    if signal is None:
        return list(windows)
    step = max(int(period_ns), 10_000_000)
    out: list[tuple[int, int | None]] = []
    for start, stop in windows:
        place = _calmest(signal, int(start), max(int(start) - int(length_ns), int(first_ns)),
                         int(start), int(warmup_ns), step, False)
        out.append((int(start), stop) if place == int(start)
                   else (place, place + int(length_ns)))
    return out


def seams_placed_note(nominal: Sequence[int], seams: Sequence[int], first_ns: int,
                      wheels: WheelSamples | None) -> str:
    """Return the one-line account of where the seams were placed (s from the first cloud)."""
    if turn_signal(wheels) is None:
        return ('chunk seams every chunk length from the first cloud (no wheel speeds to place '
                'them where the robot turns least)')
    moved = sum(1 for a, b in zip(nominal, seams) if a != b)
    places = ', '.join(f'{(s - first_ns) * 1e-9:.1f}' for s in seams)
    was = ', '.join(f'{(s - first_ns) * 1e-9:.1f}' for s in nominal)
    return (f'chunk seams at {places} s from the first cloud (nominal {was}): {moved} moved, '
            'within a quarter chunk, to where the wheels turn least over the warm-up')
