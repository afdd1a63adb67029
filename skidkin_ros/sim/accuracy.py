"""How accurate is an estimated trajectory against the simulator's truth: relative pose errors.

The calibrator uses the ground truth's increments over 2 m segments and the diagnosis its
velocities over fractions of a second, never its global frame, so a ground truth is judged here
by its increments (relative pose error, as evo's RPE): for each valid pose i, the pose j one
horizon later (``horizon_s`` in time, or ``horizon_m`` of true path), the estimated motion
i -> j against the true one (:func:`skidkin_ros.core.calibration.evaluation.motion_errors`, the
calibrator's own comparison: replayed from the true pose i, the error in its frame, yaw
wrapped). Position error in m, yaw error in rad.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from skidkin_ros.core.calibration.evaluation import motion_errors
from skidkin_ros.core.drive import path_length_m, PoseTrack
from skidkin_ros.core.timeunits import s_to_ns

__all__ = ['IncrementErrors', 'increment_errors']

TruthFn = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class IncrementErrors:
    """Position (m) and yaw (rad) errors of every increment of one horizon."""

    horizon: str
    position_m: np.ndarray
    yaw_rad: np.ndarray

    def __len__(self) -> int:
        return int(self.position_m.size)

    @property
    def median_position_m(self) -> float:
        return float(np.median(self.position_m)) if len(self) else float('nan')

    @property
    def median_yaw_rad(self) -> float:
        return float(np.median(self.yaw_rad)) if len(self) else float('nan')

    def percentile(self, q: float) -> tuple[float, float]:
        """Return the q-th percentile of the position (m) and yaw (rad) errors."""
        if not len(self):
            return float('nan'), float('nan')
        return (float(np.percentile(self.position_m, q)),
                float(np.percentile(self.yaw_rad, q)))


def increment_errors(track: PoseTrack, truth_at: TruthFn, *, horizon_s: float | None = None,
                     horizon_m: float | None = None, valid_only: bool = True) -> IncrementErrors:
    """Return the errors of the track's increments over one horizon (time or true distance).

    ``truth_at(t_ns)`` gives the true base poses (N, 3) at the track's stamps (e.g.
    ``Simulation.pose_at``). With ``valid_only``, increments touching an invalid pose are left
    out, as the calibrator leaves out such segments.
    """
    if (horizon_s is None) == (horizon_m is None):
        raise ValueError('give exactly one of horizon_s and horizon_m')
    t_ns = track.t_ns
    est = track.poses
    true = np.asarray(truth_at(t_ns), dtype=float)
    true[:, 2] = np.unwrap(true[:, 2])
    if horizon_s is not None:
        j = np.searchsorted(t_ns, t_ns + s_to_ns(horizon_s))
        label = f'{horizon_s:g} s'
    else:
        path = path_length_m(true[:, 0], true[:, 1])
        j = np.searchsorted(path, path + horizon_m)
        label = f'{horizon_m:g} m'
    i = np.arange(t_ns.size)
    keep = j < t_ns.size
    i, j = i[keep], j[keep]
    if valid_only and i.size:
        bad = np.concatenate([[0], np.cumsum(~track.valid)])
        keep = (bad[j + 1] - bad[i]) == 0
        i, j = i[keep], j[keep]
    err = motion_errors(est[i], est[j], true[i], true[j])
    return IncrementErrors(label, np.hypot(err[:, 0], err[:, 1]), np.abs(err[:, 2]))
