"""Online calibration: a change of ground caught early and learned from its own metres only.

Three rules that make the first metres on a new ground cheaper (the recipe is in
:mod:`skidkin_ros.core.online.calibrator`; the methods are those of its ``OnlineCalibrator``, a
mixin):

* **Early detection** (:meth:`ChangeLearner._probe`): every ``PROBE_M`` of reference path
  (or ``PROBE_RAD`` of turning), the segment in progress is scored under the active ground
  (its NEES against the predictive covariance, parameter uncertainty included). When that
  alone would pass the CUSUM threshold, the segment is cut there and learned at once (the
  change is declared on it), instead of waiting for the calibrator's 2 m or 1 rad. Only a
  part of at least ``PROBE_M`` of path or ``CUT_MIN_RAD`` of turning is cut: a slip on a short
  turn in place is a transient, which the whole segment's CUSUM weighs.
* **The change point** (:meth:`ChangeLearner._after_change`): the segment that revealed the
  change is mostly the old ground. The change is located on the stored reference poses as the
  last pose up to which the old ground still explains the segment (NEES below the 99 % chi2);
  the ground taken (new or remembered) learns only from there on.
* **Provisional steps while adapting**: every ``PROBE_M`` of path, the segment still growing
  is solved together with the window (:meth:`WindowSolver._provisional`, not kept): a new ground's
  parameters follow its first metres.

Cost: one rollout of the segment in progress (with its sensitivities) every ``PROBE_M`` of path,
one window solve per probe while adapting; the change point scores the revealing segment's
poses once per change. None of it runs per wheel sample.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from skidkin_ros.core.calibration.fitting import segment_errors
from skidkin_ros.core.calibration.noise_fit import mahalanobis
from skidkin_ros.core.calibration.segments import SegmentSet
from skidkin_ros.core.online.grounds import CHI2_99_3DOF, Ground
from skidkin_ros.core.online.window import _stack

if TYPE_CHECKING:
    from skidkin_ros.core.online.gates import _Ref

__all__ = ['ChangeLearner', 'LOCATED_KEEP', 'PROBE_M', 'PROBE_RAD']

# Reference path (m) or turning (rad) between two probes of the segment in progress.
PROBE_M = 0.5
PROBE_RAD = 0.25
# A part of a segment turning less than this (and shorter than PROBE_M) is never cut early.
CUT_MIN_RAD = 0.5
# A new ground learns from the located change part from this share of its poses on (its later
# half): the change lies somewhere in it (see ChangeLearner._after_change).
LOCATED_KEEP = 0.5


class ChangeLearner:
    """Early detection, change point and provisional steps of :class:`OnlineCalibrator`."""

    _probed = (-math.inf, 0.0)    # reference path and heading at the last probe

    def _accept(self, ref: _Ref) -> None:
        start = self._seg_start
        super()._accept(ref)
        if self._seg_start is ref:   # a segment ended here (learned or not), or one began
            if start is not None and start is not ref:
                self._segment_ended(start, ref)
            self._segment_began()
        self._probe(ref)

    def _probe(self, ref: _Ref) -> None:
        """Score (and, while adapting, solve) the segment in progress every PROBE_M."""
        start = self._seg_start
        if start is None or start is ref or (ref.path_m - start.path_m < PROBE_M
                                             and abs(ref.yaw - start.yaw) < PROBE_RAD):
            return
        last_m, last_yaw = self._probed
        if 0.0 <= ref.path_m - last_m < PROBE_M and abs(ref.yaw - last_yaw) < PROBE_RAD:
            return
        self._probed = (ref.path_m, ref.yaw)
        if self._seg_version != self.version:   # the ground switched in this segment
            return
        seg = self._segment(start, ref)
        if seg is None:
            return
        ground = self.active
        motion = self._motion_cov(seg)
        params = self.params
        threshold = params.cusum_threshold + params.cusum_drift - self.cusum
        # without the parameter term first (one rollout): that term only lowers the NEES
        if ((ref.path_m - start.path_m >= PROBE_M or abs(ref.yaw - start.yaw) >= CUT_MIN_RAD)
                and self._score(ground, seg, motion, False)[2] > threshold
                and self._score(ground, seg, motion, True)[2] > threshold):
            self.counters['online_early_cut'] += 1
            self._learn(start, ref)
            self._segment_ended(start, ref)
            self._seg_start = ref
            self._seg_version = self.version
            self._segment_began()
            return
        if self.travel_m < self._adapt_until_m and ground.window:
            self._provisional(seg, motion + self._reference_cov())
            self._seg_version = self.version

    def _after_change(self, a: _Ref, b: _Ref, old: Ground) -> SegmentSet | None:
        """Return the part of the revealing segment a -> b after the located change, or None.

        The change is placed at the last stored reference pose c up to which the old ground
        explains a -> c (NEES on the noise rates and the reference noise below the 99 % chi2).
        The ground taken learns from the later part of c -> b only, from the pose LOCATED_KEEP
        of the poses into it (None: too short to say anything): the change lies somewhere in
        c -> b, and a transient of the old ground just before it (a turn reversed in a spin)
        fails the test early and puts c before the change. Long-stretch seed 1: c 0.5 s before
        the change, at a turn reversal; learned from c on, the new ground's yaw rate stayed
        4-5 % off (the located part's residual under the new ground's true parameters
        0.053 rad) for 1.5 rad of spinning.
        """
        refs = [r for r in self._refs if a.t_ns < r.t_ns < b.t_ns]
        if not refs:
            return self._segment(a, b)
        parts = [self._segment(a, r) for r in refs]
        keep = [i for i, seg in enumerate(parts) if seg is not None]
        if not keep:
            return None
        batch = _stack([parts[i] for i in keep])
        errors = segment_errors(self.model, old.k, self.geometry, batch)
        cov = np.stack([self._rate_cov(r.path_m - a.path_m, abs(r.yaw - a.yaw))
                        for r in (refs[i] for i in keep)])
        nees = mahalanobis(cov, errors)
        below = np.flatnonzero(nees <= CHI2_99_3DOF)
        if below.size == 0:
            c = a
        else:
            c = refs[keep[int(below[-1])]]
        self.counters['online_change_point'] += 1
        if self.options.too_still(b.path_m - c.path_m, b.yaw - c.yaw):
            return None
        # the later part of c -> b only: a transient before the change can place c early
        tail = [r for r in self._refs if c.t_ns <= r.t_ns < b.t_ns]
        if len(tail) >= 2:
            c = tail[int(LOCATED_KEEP * len(tail))]
            if self.options.too_still(b.path_m - c.path_m, b.yaw - c.yaw):
                return None
        return self._segment(c, b)

    def _rate_cov(self, path: float, rot: float, reference: bool = True) -> np.ndarray:
        """Return a diagonal covariance from the noise rates (and the reference noise)."""
        var_x, var_y, var_yaw = self.noise.step_variances(path, rot)
        cov = np.diag([var_x + self.noise.var_x_const, var_y + self.noise.var_y_const,
                       var_yaw + self.noise.var_yaw_const]) + 1e-9 * np.eye(3)
        return cov + self._reference_cov() if reference else cov
