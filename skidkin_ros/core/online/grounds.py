"""Online calibration: the ground bank and its change detector (step 5 of the recipe).

The grounds the calibrator remembers (:class:`Ground`), the CUSUM of a segment's NEES that
detects a change of ground (a remembered ground taken back, or a new one started), and the
recognition of the ground that explains the last ``switch_window`` metres best. The methods are
those of :class:`~skidkin_ros.core.online.calibrator.OnlineCalibrator` (a mixin; the recipe is in
that module's docstring).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import TYPE_CHECKING

import numpy as np

from skidkin_ros.core.calibration.fitting import segment_errors
from skidkin_ros.core.calibration.noise_fit import mahalanobis, parameter_sensitivity
from skidkin_ros.core.calibration.segments import SegmentSet

if TYPE_CHECKING:
    from skidkin_ros.core.online.gates import _Ref

__all__ = ['Ground', 'GroundBank', 'CHI2_99_3DOF']

# A remembered ground is taken back by the recognition with switch_margin when the ground last
# changed within this many metres of reference path, else with STRICT_MARGIN x switch_margin.
RECENT_SWITCH_M = 10.0
STRICT_MARGIN = 4.0
# A ground whose segment NEES is below this (chi2, 3 dof, 99 %) explains the segment.
CHI2_99_3DOF = 11.34


@dataclass
class Ground:
    """One ground: its parameters, prior, window of segments and information.

    Information matrices are in units of each parameter's typical magnitude. ``anchor`` and
    ``prior`` are the prior (where the ground started, how sure of it); ``window`` the recent
    segments with their weight matrices and the travel at which they were learned.
    """

    ident: int
    k: np.ndarray
    prior: np.ndarray
    anchor: np.ndarray = None
    info: np.ndarray = None
    window: list = field(default_factory=list)
    learned_m: float = 0.0
    segments: int = 0
    last_used: int = 0
    remembered: bool = False   # from the file's online.grounds.* (remembered.py)

    def __post_init__(self) -> None:
        if self.anchor is None:
            self.anchor = self.k.copy()
        if self.info is None:
            self.info = self.prior.copy()


class GroundBank:
    """The grounds of :class:`OnlineCalibrator`: scored, changed, recognised (a mixin)."""

    _switched_m = -math.inf    # reference travel at the last change or switch of ground
    _changed_m = -math.inf     # reference travel at the last new ground

    def _reference_cov(self) -> np.ndarray:
        sx, syaw = self.reference_sigmas()   # measured or configured (refnoise.py)
        return np.diag([2 * sx * sx, 2 * sx * sx, 2 * syaw * syaw])

    def _score(self, ground: Ground, seg: SegmentSet, motion_cov: np.ndarray,
               with_parameters: bool) -> tuple[np.ndarray, np.ndarray | None, float]:
        """Return (residual, sensitivity or None, NEES) of a segment under one ground."""
        e = segment_errors(self.model, ground.k, self.geometry, seg)[0]
        cov = motion_cov + self._reference_cov()
        sens = None
        if with_parameters:
            sens = parameter_sensitivity(self.model.name, self.model.mapping(ground.k),
                                         self.geometry, seg)[0] * self.scale
            cov = cov + sens @ np.linalg.inv(ground.info) @ sens.T
        return e, sens, float(mahalanobis(cov[None], e[None])[0])

    def _change(self, seg: SegmentSet, motion_cov: np.ndarray) -> None:
        """Take back a known ground, or start a new one (the CUSUM passed its threshold)."""
        self.cusum = 0.0
        best, best_nees = None, CHI2_99_3DOF
        for ground in self.grounds:
            if ground is self.active:
                continue
            nees = self._score(ground, seg, motion_cov, True)[2]
            if nees < best_nees:
                best, best_nees = ground, nees
        if best is not None:
            self._activate(best, 'online_switch')
            return
        ground = Ground(self._next_ident, self.active.k.copy(), self.prior_info.copy())
        self._next_ident += 1
        self._forget_unconfirmed()   # remembered grounds today's ground refuted (remembered.py)
        if len(self.grounds) >= int(self.params.max_grounds):
            oldest = min((g for g in self.grounds if g is not self.active),
                         key=lambda g: g.last_used, default=None)
            if oldest is not None:
                self.grounds.remove(oldest)
            else:
                self.grounds.remove(self.active)
        self.grounds.append(ground)
        self._adapt_until_m = self.travel_m + self.params.adapt_distance
        self._changed_m = self.travel_m
        self._activate(ground, 'online_change')
        self._warn('online_change', f'change of ground detected: learning ground {ground.ident} '
                   f'from the current parameters ({len(self.grounds)} grounds known)')

    def _forget_unconfirmed(self) -> None:
        """Forget the file's remembered grounds not learned on yet: a new ground refuted them.

        A new ground starts only where no remembered ground explains the segment; one from the
        file that was never learned on today (the active one included: the recognition took it
        on a short window) is yesterday's, not today's: kept, it won the recognition's window
        on today's ground and flickered with the new one, neither learning (a third ground's
        drive: 1.25x the eps_t of starting without it).
        """
        keep = [g for g in self.grounds if not g.remembered or g.segments]
        if len(keep) < len(self.grounds):
            self.counters['online_grounds_forgotten'] += len(self.grounds) - len(keep)
            self.grounds[:] = keep

    def _note_error(self, seg: SegmentSet, residual: np.ndarray) -> None:
        """Keep the error the old ground made on the segment that revealed the change.

        The odometry carried that error already, with a covariance that did not know the ground
        had changed: the odometer adds it (world frame, e e^T) to the published covariance once
        (:meth:`take_error`), so the covariance stays honest across a change.
        """
        c, s = math.cos(float(seg.start[0, 2])), math.sin(float(seg.start[0, 2]))
        world = np.array([c * residual[0] - s * residual[1], s * residual[0] + c * residual[1],
                          residual[2]])
        self._error = self._error + np.outer(world, world)

    def take_error(self) -> np.ndarray | None:
        """Return the error noted since the last call (3 x 3, world frame), or None."""
        error, self._error = self._error, np.zeros((3, 3))
        return error if error.any() else None

    def _switch_margin(self) -> float:
        """Return the NEES margin a remembered ground must win by to be taken back.

        ``switch_margin`` where the ground changed within the last ``RECENT_SWITCH_M`` metres
        (grounds that alternate: a switch is likely, take it at once); ``STRICT_MARGIN`` times
        that after a long stretch of one ground, where a switch is rare (the prior of a switch
        follows the recent switching, as the transition matrix of an interacting-multiple-model
        filter would): one odd window does not take the old ground back.
        """
        margin = self.params.switch_margin
        if self.travel_m - self._switched_m > RECENT_SWITCH_M:
            margin *= STRICT_MARGIN
        return margin

    def _young(self, ground: Ground) -> bool:
        """Tell whether a ground is scored with its parameter uncertainty (a new one, adapting).

        A ground started at a change knows only its first metres: its values are still far off
        in the directions those metres hardly observed (a spin in place tells alpha / y, not
        alpha), while the ground it left is well known. Scored on its values alone, it lost the
        window to the ground it left, which the change had just refuted (long-stretch seed 41:
        back on the old ground 0.7 m after the change, for 1.6 m); with its parameter
        uncertainty in the NEES (as the change detection scores the active ground) it is judged
        by what it can be, not by its first guess. A learned ground's uncertainty is small.
        """
        return ground is self.active and self.travel_m < self._adapt_until_m

    def _activate(self, ground: Ground, cause: str) -> None:
        self._switched_m = self.travel_m
        self.counters[cause] += 1
        self.active = ground
        ground.last_used = self.counters['online_segments'] + self.counters[cause]
        self.version += 1

    def _recognise(self, ref: _Ref) -> None:
        """Score the last switch_window metres under every ground; take a clearly better one."""
        refs = self._refs
        window = self.params.switch_window
        if ref.path_m - refs[0].path_m < window:
            return
        start = refs[0]
        for item in refs:
            if item.path_m > ref.path_m - window:
                break
            start = item
        path = ref.path_m - start.path_m
        if path > self.travel_m - self._changed_m:
            return   # the window starts before a new ground began: it would judge a blend
        seg = self._segment(start, ref)
        if seg is None:
            return
        rot = abs(ref.yaw - start.yaw)
        # a diagonal weight from the noise rates (the grounds are compared on the same one)
        var_x, var_y, var_yaw = self.noise.step_variances(path, rot)
        motion_cov = np.diag([var_x + self.noise.var_x_const, var_y + self.noise.var_y_const,
                              var_yaw + self.noise.var_yaw_const]) + 1e-9 * np.eye(3)
        scores = [(self._score(g, seg, motion_cov, self._young(g)), g) for g in self.grounds]
        active, residual = next((s[2], s[0]) for s, g in scores if g is self.active)
        best, ground = min(((s[2], g) for s, g in scores), key=lambda item: item[0])
        if ground is not self.active and active - best > self._switch_margin():
            self._note_error(seg, residual)
            self._activate(ground, 'online_switch')
            self.cusum = 0.0
