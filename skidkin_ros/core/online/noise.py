"""Online calibration: the published noise learned from the odometry's own recent errors.

The file's noise model was fitted on one ground with the right parameters. Online, the odometry
also errs where the ground changed before the change was seen, where two grounds alternate
faster than they are recognised, and with parameters still being learned: the published
covariance must cover that too. The calibrator's coverage rule
(:func:`~skidkin_ros.core.calibration.noise_fit.coverage_scale`: the smallest factor >= 1 on
all the noise values that puts 95 % of the errors inside their predicted 95 % region) is applied
to the last ``NOISE_WINDOW`` segments' errors of the odometry as it ran (the parameters in
force when each segment began, every segment, including those during which the ground
switched and which are not learned from), with the segment covariance of
:func:`~skidkin_ros.core.calibration.noise_fit.segment_motion` (the parameter covariance as its
fixed term). The published noise is the file's times that factor: it widens where the odometry
errs more than the file says and comes back to the file's (never below it) where it does not.
The learning itself keeps the file's noise (its weights and change detection are unchanged).

The methods are those of :class:`~skidkin_ros.core.online.calibrator.OnlineCalibrator` (a mixin).
"""

from __future__ import annotations

import collections
from typing import TYPE_CHECKING

import numpy as np

from skidkin_ros.core.calibration.fitting import segment_errors
from skidkin_ros.core.calibration.noise_fit import (coverage_scale, segment_motion,
                                                    SegmentMotion)
from skidkin_ros.core.odometry.noise import NoiseModel

if TYPE_CHECKING:
    from skidkin_ros.core.online.gates import _Ref

__all__ = ['NoiseLearner', 'NOISE_WINDOW', 'NOISE_MIN_SEGMENTS']

# Segments whose errors set the published noise (the most recent), and the fewest that may.
NOISE_WINDOW = 32
NOISE_MIN_SEGMENTS = 4


class NoiseLearner:
    """The published noise of :class:`OnlineCalibrator` (a mixin)."""

    noise_scale = 1.0
    _seg_k: np.ndarray | None = None

    def _noise_window(self) -> collections.deque:
        window = self.__dict__.get('_noise_items')
        if window is None:
            window = self._noise_items = collections.deque(maxlen=NOISE_WINDOW)
        return window

    def published_noise(self) -> NoiseModel:
        """Return the noise the odometry publishes with: the file's times the learned factor."""
        if self.noise_scale == 1.0:
            return self.noise
        return NoiseModel(*(value * self.noise_scale for value in self.noise.as_dict().values()))

    def _noise_motion(self, k: np.ndarray, seg) -> SegmentMotion:
        """Return one segment's noise bases under parameters k (fixed term: their covariance).

        An augmented model overrides this.
        """
        return segment_motion(self.model.name, self.model.mapping(k), self.geometry, seg,
                              self.covariance)

    def _segment_began(self) -> None:
        """Keep the parameters in force at the start of a segment."""
        self._seg_k = self.active.k.copy()

    def _segment_ended(self, a: _Ref, b: _Ref) -> None:
        """Add the odometry's error over a -> b; set the factor again (coverage rule)."""
        k = self._seg_k
        if k is None or self.options.too_still(b.path_m - a.path_m, b.yaw - a.yaw):
            return
        seg = self._segment(a, b)
        if seg is None:
            return
        error = segment_errors(self.model, k, self.geometry, seg)[0]
        motion = self._noise_motion(k, seg)
        window = self._noise_window()
        window.append((error, motion))
        if len(window) < NOISE_MIN_SEGMENTS:
            return
        errors = np.stack([item[0] for item in window])
        joined = SegmentMotion.concat([item[1] for item in window])
        # the reference's own noise is in the errors: the fixed term carries it
        fixed = np.zeros((len(errors), 3, 3)) if joined.fixed is None else joined.fixed
        joined = SegmentMotion(joined.basis_x, joined.basis_y, joined.basis_yaw_m,
                               joined.basis_yaw_rad, joined.basis_const,
                               fixed + self._reference_cov(), joined.basis_time)
        scale = coverage_scale(self.noise, errors, joined)
        if abs(scale - self.noise_scale) > 1e-3 * self.noise_scale:
            self.noise_scale = scale
            self.counters['online_noise_updates'] += 1
            in_step = self._seg_version == self.version   # not a change of parameters
            self.version += 1
            if in_step:
                self._seg_version = self.version
