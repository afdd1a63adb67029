"""Online calibration: the window re-solve of the active ground (step 6 of the recipe).

The ground's window of segments, faded by the path travelled and relinearised at the current
parameters, gives one Gauss-Newton step in the directions the data observes (information form,
the ground's prior keeping the others). The methods are those of
:class:`~skidkin_ros.core.online.calibrator.OnlineCalibrator` (a mixin; the recipe is in that
module's docstring).
"""

from __future__ import annotations

import math

import numpy as np

from skidkin_ros.core.calibration.fitting import segment_errors
from skidkin_ros.core.calibration.noise_fit import (parameter_sensitivity, segment_covariances,
                                                    segment_motion)
from skidkin_ros.core.calibration.segments import SegmentSet
from skidkin_ros.core.online.grounds import Ground
from skidkin_ros.errors import ParameterError

__all__ = ['WindowSolver']


class WindowSolver:
    """The window re-solve of :class:`OnlineCalibrator` (a mixin)."""

    def _motion_cov(self, seg: SegmentSet) -> np.ndarray:
        motion = segment_motion(self.model.name, self.model.mapping(self.active.k),
                                self.geometry, seg)
        return segment_covariances(self.noise, motion)[0]

    def _residuals(self, ground: Ground, segments: list[SegmentSet]
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Return the residuals (N, 3) and their sensitivities (N, 3, p; scaled units)."""
        batch = _stack(segments)
        errors = segment_errors(self.model, ground.k, self.geometry, batch)
        sens = parameter_sensitivity(self.model.name, self.model.mapping(ground.k),
                                     self.geometry, batch) * self.scale
        return errors, sens

    def _update(self, seg: SegmentSet, cov: np.ndarray, path_m: float,
                errors: np.ndarray | None = None, sens: np.ndarray | None = None) -> None:
        """Add the segment to the window; one Gauss-Newton step in the observable directions.

        The window's segments fade by exp(-path / memory) at every new segment (forgetting:
        faster while adapting, and what faded then stays faded) and are
        relinearised at the current parameters (no early linearisation stays baked in, as in a
        plain recursive filter); the prior (the ground's start, its information) keeps the
        unobserved directions where they were and bounds their uncertainty. ``errors`` and
        ``sens``: the residuals of the window and the segment at the current parameters, when
        known (None: computed here).
        """
        ground = self.active
        params = self.params
        memory = params.adapt_memory if self.travel_m < self._adapt_until_m else params.memory
        fade = math.exp(-path_m / memory)
        for item in ground.window:
            item[2] *= fade
        items = ground.window + [[seg, np.linalg.inv(cov), 1.0]]
        first = max(len(items) - int(params.window), 0)
        keep = [i for i in range(first, len(items)) if items[i][2] > 1e-3]
        ground.window = [items[i] for i in keep]
        self.counters['online_segments'] += 1
        ground.segments += 1
        ground.learned_m += path_m
        ground.last_used = self.counters['online_segments']
        if errors is None or len(errors) != len(items):
            e, sens = self._residuals(ground, [item[0] for item in ground.window])
        else:
            e, sens = errors[keep], sens[keep]
        self._solve(ground, ground.window, e, sens)

    def _provisional(self, seg: SegmentSet, cov: np.ndarray) -> None:
        """One Gauss-Newton step on the window plus a segment still growing (not kept).

        While adapting to a new ground, the segment in progress is solved with the window every
        ``PROBE_M`` of path (:mod:`skidkin_ros.core.online.adapt`): the new ground's parameters
        follow the first metres on it instead of waiting for a whole segment.
        """
        ground = self.active
        items = ground.window + [[seg, np.linalg.inv(cov), 1.0]]
        e, sens = self._residuals(ground, [item[0] for item in items])
        self.counters['online_provisional'] += 1
        self._solve(ground, items, e, sens)

    def _solve(self, ground: Ground, items: list, e: np.ndarray, sens: np.ndarray,
               min_information: float | None = None) -> None:
        """Take the Gauss-Newton step of ``items`` in the observable directions.

        ``e``, ``sens``: the items' residuals and sensitivities at the ground's parameters; the
        ground's prior holds the directions the items do not observe. ``min_information``:
        the threshold of an observed direction (None: online.min_information).
        """
        params = self.params
        if min_information is None:
            min_information = params.min_information
        weights = np.array([item[2] for item in items])
        inverse = np.stack([item[1] for item in items]) * weights[:, None, None]
        data = np.einsum('nip,nij,njq->pq', sens, inverse, sens)
        data = 0.5 * (data + data.T)
        u_offset = (ground.k - ground.anchor) / self.scale
        gradient = np.einsum('nip,nij,nj->p', sens, inverse, e) - ground.prior @ u_offset
        ground.info = data + ground.prior
        values, vectors = np.linalg.eigh(data)
        observed = values >= max(min_information, 1e-9 * max(values.max(), 0.0))
        if not observed.any():
            self.counters['online_unobservable'] += 1
            return
        basis = vectors[:, observed]
        step = basis @ np.linalg.solve(basis.T @ ground.info @ basis, basis.T @ gradient)
        largest = float(np.max(np.abs(step)))
        if largest > params.prior_sigma:
            # one update moves no parameter by more than the prior's width (typical magnitudes):
            # one segment of a real reference's glitch moved b_hat from 0.555 to 0 (C269)
            step = step * (params.prior_sigma / largest)
            self.counters['online_step_limited'] += 1
        k = _toward_bounds(ground.k, ground.k + step * self.scale, self._lo, self._hi)
        try:
            self.model.check_constraints(k)
        except ParameterError:
            self.counters['online_update_refused'] += 1
            return
        ground.k = k
        self.version += 1


def _toward_bounds(k0: np.ndarray, k1: np.ndarray, lo: np.ndarray, hi: np.ndarray
                   ) -> np.ndarray:
    """Return k1, each parameter that crosses a bound stopped half way to it.

    One Gauss-Newton step from far off (the ideal file on the real Husky: yaw rates 2x off)
    can leave the range; clipped, it landed on the bound (b_hat at 0: an infinite yaw rate,
    every later reference pose refused as a jump, nothing learned again; C269). A parameter
    already on its bound is clipped. Only the parameter that crosses is cut: cutting the
    whole step held every other parameter back for good once one sat near a bound it keeps
    being pushed to (a lag or slip of 0, the bound: room halves each update, and so does
    every other parameter's step; C289).
    """
    d = k1 - k0
    room = np.where(d < 0, k0 - lo, hi - k0)
    limit = ((k1 < lo) | (k1 > hi)) & (room > 0)
    k = k1.copy()
    k[limit] = k0[limit] + 0.5 * np.sign(d[limit]) * room[limit]
    return np.clip(k, lo, hi)


def _stack(segments: list[SegmentSet]) -> SegmentSet:
    """Return one-row segment sets as one set, padded with dt = 0 to the longest."""
    if len(segments) == 1:
        return segments[0]
    width = max(seg.dt_s.shape[1] for seg in segments)

    def pad(name: str) -> np.ndarray:
        out = np.zeros((len(segments), width))
        for i, seg in enumerate(segments):
            row = getattr(seg, name)[0]
            out[i, :row.size] = row
        return out
    # the first set's class: a learner's own segment layout (augmented.py's pairs) is kept
    return type(segments[0])(
        drive=np.zeros(len(segments), dtype=int),
        t_a_ns=np.concatenate([seg.t_a_ns for seg in segments]),
        t_b_ns=np.concatenate([seg.t_b_ns for seg in segments]),
        start=np.concatenate([seg.start for seg in segments]),
        end=np.concatenate([seg.end for seg in segments]),
        omega_l=pad('omega_l'), omega_r=pad('omega_r'), dt_s=pad('dt_s'),
        path_m=np.concatenate([seg.path_m for seg in segments]))
