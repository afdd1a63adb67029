"""Online calibration: the reference's own noise, measured from its poses against the wheels.

``online.sigma_xy`` and ``online.sigma_yaw`` say how noisy each reference pose is; they weigh
every learning segment (the reference noise at both ends) and set how large a segment's error
must be before it reveals a change of ground. Most users leave the defaults (2 cm, 0.005 rad),
which are twice what a good lidar odometry gives: the segments are then weighed as if the
reference were noisier than it is, and a change is seen later.

The white noise of each pose shows in the second difference of the reference's increments
against the wheels': between two accepted poses, the reference's displacement (x, y) less the
wheels' travel along the reference's heading, and its heading change less the wheels'
rotation. A model error (slip, a wrong parameter, a change of ground) changes slowly from one
0.1 s interval to the next and cancels in the difference of two such increments; three poses'
white noise remains, with variance ``6 sigma^2`` per axis (the middle pose counts twice). Of
the last ``REF_NOISE_KEEP`` squared second differences, the median over ``6 x 0.455`` (the
median of a chi-square with one degree of freedom) and the mean over 6, each square cut where
the bound below stops, both estimate that variance; the larger is used: the median alone took a
reference exact but for a few poses far off (an ICP snapping into a wrong minimum for a scan)
as exact, and the cut keeps a single jump the gates let through from moving the mean far. A
pose that repeats the last one exactly is no measurement (a relay republishing a slower
reference's last pose): no difference is taken across it.

The sigmas used (:meth:`RefNoiseLearner.reference_sigmas`) are the configured ones until
``REF_NOISE_MIN`` second differences are in, then the measured ones, kept within
``REF_NOISE_RANGE`` times the configured value either way: a reference whose error is
correlated over seconds (a drifting lidar odometry) shows little of it in 0.1 s differences,
and the configured value keeps its say. The methods are those of
:class:`~skidkin_ros.core.online.calibrator.OnlineCalibrator` (a mixin).
"""

from __future__ import annotations

import collections
import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from skidkin_ros.core.online.gates import _Ref

__all__ = ['RefNoiseLearner', 'REF_NOISE_KEEP', 'REF_NOISE_MIN', 'REF_NOISE_RANGE']

# Second differences kept (the last 30 s at 10 Hz) and needed before the measure is used.
REF_NOISE_KEEP = 300
REF_NOISE_MIN = 100   # (positions: two per pose, x and y)
# The measured sigma stays within [configured / RANGE, configured * RANGE].
REF_NOISE_RANGE = 4.0
# Recompute the medians after this many new second differences.
REF_NOISE_EVERY = 20
# Median of a chi-square with one degree of freedom, times 6 (three poses' noise).
_MEDIAN_CHI2_1_X6 = 6.0 * 0.454936


class RefNoiseLearner:
    """The reference noise of :class:`OnlineCalibrator`, measured as it drives (a mixin)."""

    _ref_sigmas: tuple[float, float] | None = None   # measured (xy, yaw); None: configured
    _ref_last = None          # (x, y, heading) of the reference's last increment less the wheels'
    _ref_new = 0              # second differences since the medians were last computed

    def _ref_noise_buffers(self) -> tuple[collections.deque, collections.deque]:
        if '_ref_d2' not in self.__dict__:
            self._ref_d2 = (collections.deque(maxlen=REF_NOISE_KEEP),
                            collections.deque(maxlen=REF_NOISE_KEEP))
        return self._ref_d2

    def reference_sigmas(self) -> tuple[float, float]:
        """Return the (position m, heading rad) standard deviations of a reference pose in use."""
        if self._ref_sigmas is None:
            return self.params.sigma_xy, self.params.sigma_yaw
        return self._ref_sigmas

    def _accept(self, ref: _Ref) -> None:
        last = self._refs[-1] if self._refs else None
        if last is not None:
            self._measure_reference(last, ref)
        super()._accept(ref)

    def _start_chain(self, t_ns: int, x: float, y: float, yaw: float) -> None:
        self._ref_last = None     # a gap or a restart: no difference across it
        super()._start_chain(t_ns, x, y, yaw)

    def _measure_reference(self, last: _Ref, ref: _Ref) -> None:
        """Add the second differences of the interval last -> ref and the one before it."""
        motion = self._wheel_motion(last.t_ns, ref.t_ns)
        if motion is None or (ref.x, ref.y, ref.yaw) == (last.x, last.y, last.yaw):
            # a pose repeated exactly is no new measurement (a relay republishing the last
            # pose of a slower reference, a frozen one below the stall distance): its error is
            # the motion since the reference last moved, and its zero difference would read
            # as a noise-free reference; no difference is taken across it
            self._ref_last = None
            return
        travel, rotation = motion
        dx, dy = ref.x - last.x, ref.y - last.y
        heading = 0.5 * (last.yaw + ref.yaw)
        c, s = math.cos(heading), math.sin(heading)
        # the wheels' displacement along the reference's heading (travel is |v_x| dt: the sign
        # of the reference's own displacement along its heading)
        step = travel if dx * c + dy * s >= 0.0 else -travel
        current = (dx - step * c, dy - step * s, ref.yaw - last.yaw - rotation)
        before, self._ref_last = self._ref_last, current
        if before is None:
            return
        xy, yaw = self._ref_noise_buffers()
        xy.append((current[0] - before[0]) ** 2)
        xy.append((current[1] - before[1]) ** 2)
        yaw.append((current[2] - before[2]) ** 2)
        self._ref_new += 1
        if self._ref_new >= REF_NOISE_EVERY:
            self._ref_new = 0
            self._ref_sigmas = self._measured_sigmas(xy, yaw)

    def _measured_sigmas(self, xy: collections.deque, yaw: collections.deque
                         ) -> tuple[float, float] | None:
        params = self.params
        out = []
        for values, configured in ((xy, params.sigma_xy), (yaw, params.sigma_yaw)):
            if len(values) < REF_NOISE_MIN:
                out.append(configured)
                continue
            sigma = _sigma(np.fromiter(values, float), configured)
            out.append(min(max(sigma, configured / REF_NOISE_RANGE),
                           configured * REF_NOISE_RANGE))
        measured = (out[0], out[1])
        return None if measured == (params.sigma_xy, params.sigma_yaw) else measured


def _sigma(squares: np.ndarray, configured: float) -> float:
    """Return the noise of one pose from squared second differences (the module docstring).

    The larger of two: the median's (the white noise of most poses) and the mean's with each
    square cut where the bound stops (a few poses far off, a reference that snaps 10 cm for one
    scan in seven: the median sees only the exact majority; weighed as if exact, those poses
    made five false changes of ground). A single jump moves the mean by at most the bound over
    the number kept.
    """
    cap = 6.0 * (configured * REF_NOISE_RANGE) ** 2
    median = float(np.median(squares)) / _MEDIAN_CHI2_1_X6
    mean = float(np.mean(np.minimum(squares, cap))) / 6.0
    return math.sqrt(max(median, mean))
