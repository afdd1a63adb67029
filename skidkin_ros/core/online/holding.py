"""Online calibration: which ground the odometry runs while the reference is missing.

Without a reference (state ``holding``: none for ``online.max_gap``) nothing tells which of the
remembered grounds is under the robot. Where one ground has lasted (long stretches, or a single
change of ground), the active ground is the best guess and is kept. Where the robot has gone
back and forth between remembered grounds lately, the active ground at the loss is right for
the first metres only: the robot will cross onto the other grounds as it did before.

The grounds are then treated as the states of a Markov chain, as an interacting-multiple-model
filter's transition matrix would: over the last ``online.memory`` metres of reference path, the
share of the path on each ground (occupancy pi) and the switches per metre (lambda). After d
metres of wheel travel since the last accepted reference pose, the probability of each ground
is ``p = pi + (delta_active - pi) exp(-mu d)`` (mu = lambda / (1 - sum pi^2): a chain that
redraws its ground from pi at rate mu switches at rate lambda), and the odometry runs the
expected parameters ``sum p_j k_j`` with the mixture's covariance ``sum p_j (Sigma_j +
(k_j - k)(k_j - k)^T)`` (the spread between the grounds is published as uncertainty). A blend
is used only when the robot went back to a ground it had driven on at least ``MIN_RETURNS``
times in that path (evidence that grounds alternate: one return can be a one-off); a new ground
that replaced the old one is a change, not an alternation. A stay shorter than
``online.switch_window`` (the recognition flickering, e.g. a false switch back right after a
change) is not counted as a stay.

Without a gyro, where stays have been completed, the chain's weights are replaced by those of
a semi-Markov chain in wheel travel that knows how long the robot has been on the last ground
and how long stays lasted (``dwell.py``); with a gyro, ``gyrochoice.py`` weighs the chain's.

When the reference returns, the active ground's own parameters are in force again at once; the
recognition (``grounds.py``) takes another ground within its first ``switch_window`` if another
explains the reference better. The ground learned, its window and what ``~/save_calibration``
writes are never the blend: only what the odometry integrates and publishes while holding.
The methods are those of :class:`~skidkin_ros.core.online.calibrator.OnlineCalibrator` (a
mixin). Cost: nothing per wheel sample while a reference comes; while holding, one blend every
``HOLD_CHECK_S`` of wheel time.
"""

from __future__ import annotations

import collections
import math

import numpy as np

from skidkin_ros.core.online import dwell
from skidkin_ros.core.timeunits import NS_PER_S
from skidkin_ros.errors import ParameterError

__all__ = ['HoldingBlend', 'HOLD_CHECK_S', 'HOLD_STEP']

# Wheel time between two looks at the blend while holding (or waiting to hold).
HOLD_CHECK_S = 0.1
# The blend's weights are set again when one moved by more than this.
HOLD_STEP = 0.02
# Ground activations remembered (each with the reference path at which it happened).
HISTORY = 256
# Returns to a ground already driven on, in the last online.memory m, that make alternation.
MIN_RETURNS = 2


class HoldingBlend:
    """The parameters in force while holding, for :class:`OnlineCalibrator` (a mixin)."""

    _blend: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # (weights, k, covariance)
    _hold_plan: tuple | None = None    # (grounds, pi, mu) chosen when holding began
    _hold_dwell: np.ndarray | None = None   # dwell.py's occupancy table for that plan
    _ref_travel = 0.0                  # the wheels' running travel at the last accepted pose

    # ------------------------------------------------------------------ what is in force
    def in_force(self) -> tuple[np.ndarray, np.ndarray]:
        """Return the parameters the odometry integrates and their covariance (their units)."""
        if self._blend is not None:
            return self._blend[1], self._blend[2]
        return self.active.k, self.covariance

    def hold_weight(self) -> float:
        """Return the active ground's weight in the parameters in force (1: no blend)."""
        return 1.0 if self._blend is None else float(self._blend[0][0])

    # ------------------------------------------------------------------ history
    def _history(self) -> collections.deque:
        history = self.__dict__.get('_activations')
        if history is None:
            history = self._activations = collections.deque(maxlen=HISTORY)
            history.append((0.0, self.grounds[0], 'start', 0.0))
        return history

    def _activate(self, ground, cause: str) -> None:
        self._history()
        super()._activate(ground, cause)
        self._history().append((self.travel_m, ground, cause, self._travel))

    def _accept(self, ref) -> None:
        super()._accept(ref)
        self._ref_travel = self._travel
        self._hold_plan = None   # a pose again: the next hold plans afresh

    def _start_chain(self, t_ns: int, x: float, y: float, yaw: float) -> None:
        super()._start_chain(t_ns, x, y, yaw)
        self._ref_travel = self._travel
        self._hold_plan = None

    # ------------------------------------------------------------------ the blend
    def _hold_plan_now(self) -> tuple | None:
        """Return (grounds, pi, mu) of the recent path, or None: keep the active ground."""
        if len(self.grounds) < 2:
            return None
        window = self.params.memory
        now = self.travel_m
        start = max(now - window, 0.0)
        history = _dwells(list(self._history()), now, self.params.switch_window)
        shares: dict[int, float] = {}
        switches = returns = 0
        seen: set[int] = set()
        for i, (at, ground) in enumerate(history):
            end = history[i + 1][0] if i + 1 < len(history) else now
            if i and at > start:
                switches += 1
                returns += id(ground) in seen
            seen.add(id(ground))
            if end > start:
                shares[id(ground)] = shares.get(id(ground), 0.0) + end - max(at, start)
        span = now - start
        if returns < MIN_RETURNS or span <= 0.0:
            return None
        grounds = [self.active] + [g for g in self.grounds
                                   if g is not self.active and shares.get(id(g), 0.0) > 0.0]
        pi = np.array([shares.get(id(g), 0.0) for g in grounds]) / span
        pi = pi / pi.sum()
        spread = 1.0 - float(pi @ pi)
        if len(grounds) < 2 or spread <= 1e-6:
            return None
        return grounds, pi, (switches / span) / spread

    def _dwell_plan(self, grounds: list) -> np.ndarray | None:
        """Return the dwell model's occupancy table (``dwell.py``) for ``grounds``, or None."""
        events = [e for e in self._history() if len(e) > 3]
        start = self.travel_m - self.params.memory
        # stays in metres of wheel travel, the hold's own clock (the reference's path also
        # sums its noise: 1.3x the true path on the study's drives, most where the robot
        # stands or spins)
        history = _dwells([(e[3], e[1], e[2]) for e in events], self._ref_travel,
                          self.params.switch_window)
        if not history or history[-1][1] is not grounds[0]:
            return None
        index = {id(g): j for j, g in enumerate(grounds)}
        recent = {e[3] for e in events if e[0] > start}
        stays, switches = [], []
        for (at, ground), (end, after) in zip(history, history[1:]):
            if end in recent and id(ground) in index:
                stays.append((index[id(ground)], end - at))
                if id(after) in index:
                    switches.append((index[id(ground)], index[id(after)]))
        if not stays or not dwell.lengths_explained(stays, self.params.switch_window):
            return None   # no stay, or stays of no typical length: the Markov chain
        return dwell.occupancy(stays, switches, len(grounds), self._ref_travel - history[-1][0],
                               self.params.switch_window)

    def _hold_check(self, t1_ns: int) -> None:
        """Set the blend in force for the travel since the reference was lost (or end it)."""
        last = self._last_accepted_wheel_ns
        gap_ns = self.params.max_gap * NS_PER_S
        holding = last is not None and t1_ns - last > gap_ns
        if not holding:
            self._hold_plan = None
            if self._blend is not None:
                self._blend = None
                self._bump()
            if last is not None and len(self.grounds) > 1:
                self._due_ns = min(self._due_ns, int(last + gap_ns) + 1)
            return
        if self._hold_plan is None:
            self._hold_plan = self._hold_plan_now() or ()
            self._hold_dwell = None
            if self._hold_plan:
                self.counters['online_hold_blend'] += 1
                if self.gyro_turn is None or self.gyro_turn(last, t1_ns) is None:
                    # no gyro (with one, gyrochoice.py's forward filter carries the chain on)
                    self._hold_dwell = self._dwell_plan(self._hold_plan[0])
                    if self._hold_dwell is not None:
                        self.counters['online_hold_dwell'] += 1
        if not self._hold_plan:
            return   # the active ground holds until a pose is accepted again
        self._due_ns = min(self._due_ns, t1_ns + int(HOLD_CHECK_S * NS_PER_S))
        grounds, pi, mu = self._hold_plan
        travel = max(self._travel - self._ref_travel, 0.0)
        if self._hold_dwell is not None:
            weights = dwell.weights_at(self._hold_dwell, travel)
        else:
            weights = pi * (1.0 - math.exp(-mu * travel))
            weights[0] += math.exp(-mu * travel)
        weights = self._gyro_weigh(t1_ns, self._hold_plan, travel, weights)   # gyrochoice.py
        if self._blend is not None and np.abs(weights - self._blend[0]).max() < HOLD_STEP:
            return
        ks = np.stack([g.k for g in grounds])
        k = weights @ ks
        scale = np.outer(self.scale, self.scale)
        cov = np.zeros((k.size, k.size))
        for w, g, kj in zip(weights, grounds, ks):
            d = kj - k
            cov += w * (np.linalg.inv(g.info) * scale + np.outer(d, d))
        try:
            self.model.check_constraints(k)
        except ParameterError:
            self.counters['online_update_refused'] += 1
            self._hold_plan = ()
            return
        self._blend = (weights, k, cov)
        self._bump()

    def _bump(self) -> None:
        """Count a change of the parameters in force (not a ground's: no straddle)."""
        in_step = self._seg_version == self.version
        self.version += 1
        if in_step:
            self._seg_version = self.version


def _dwells(events: list, now: float, shortest: float) -> list[tuple[float, object]]:
    """Return the (start, ground) of each stay on a ground, flickers of the recognition left out.

    A stay shorter than ``shortest`` (``online.switch_window``: the recognition's own window
    cannot resolve less) is not a ground the robot was on: it is dropped, and the ground before
    it goes on (a false switch back and forth right after a change is no alternation).
    """
    kept: list[tuple[float, object]] = []
    for i, event in enumerate(events):
        at, ground = event[0], event[1]
        end = events[i + 1][0] if i + 1 < len(events) else now
        if end - at < shortest and i + 1 < len(events):
            continue
        if kept and kept[-1][1] is ground:
            continue
        kept.append((at, ground))
    return kept
