"""Normalised estimation error squared (NEES) and its chi2 band: whether a covariance is honest.

For an error e (d components) predicted to be N(0, P), NEES = e^T P^-1 e follows chi2 with d
degrees of freedom. The average of N independent NEES values, times N, follows chi2 with N d
degrees of freedom, so the average lies inside [chi2.ppf(0.025, N d) / N, chi2.ppf(0.975, N d) / N]
with 95 % probability when the covariance is right (Bar-Shalom, Li and Kirubarajan 2001, 5.4).
Above the band the covariance is too small (over-confident), below it too large.

Odometry alone (:func:`segment_nees`): the held-out drives are cut with
:func:`skidkin_ros.core.calibration.segments.cut_segments` into NON-OVERLAPPING windows of a fixed
ground-truth path length (``SegmentOptions.horizon_m``, by default the calibration's evaluation
horizon h_e = 2 m; the remainder at a drive's end is dropped, as are windows without motion). Each
window is predicted independently with :func:`skidkin_ros.core.odometry.propagation.predict` from
the TRUE start pose with a ZERO covariance, over the drive's own wheel samples; its end-pose error
(start frame, yaw wrapped) is scored against the propagated covariance. Windows share no wheel
sample and start from the truth, so their errors are independent as far as the odometry error is
white; what is left of systematic model error correlates them, which the band does not allow
for (a reason to read the band as a check, not a proof).

Odometry over whole drives (:func:`drive_nees`): each held-out drive is predicted from its true
start pose with a zero covariance by :func:`skidkin_ros.core.odometry.propagation.predict_track`
(the node's propagator: per-metre noise, length-independent part, parameter covariance), and the
error is scored at the first sample where the ground-truth path reaches each distance (1 m to the
drive's length) and at checkpoints every ``checkpoint_s``. At one distance the M drives give M
independent values (the band for M runs); the checkpoints of one drive are not independent, so
their pooled average is a summary, not a test. Windows test the noise at one horizon; whole drives
add what a window cannot show: the parameter error, the same for the whole drive, whose effect
grows in proportion to the distance.

A filter over time (:func:`nees_over_time`): with M independent runs (held-out drives) the NEES
at each time step is averaged over the runs and compared with the band for M runs (N = M); the
share of time steps inside that band should be close to 95 %.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import stats

from skidkin_ros.core.calibration.noise_fit import MIN_VARIANCE
from skidkin_ros.core.calibration.segments import cut_segments, segment_frame_error, SegmentOptions
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.odometry.integrator import TwistSource, wrap_angle
from skidkin_ros.core.odometry.interval import DEFAULT_INTERVAL, held_wheels
from skidkin_ros.core.odometry.noise import NoiseModel
from skidkin_ros.core.odometry.propagation import predict, predict_track
from skidkin_ros.core.odometry.uncertainty import ParameterUncertainty
from skidkin_ros.errors import DataError

__all__ = ['nees', 'chi2_band', 'NeesSummary', 'summarize_nees', 'SegmentNees', 'segment_nees',
           'NeesOverTime', 'nees_over_time', 'DriveNees', 'drive_nees']


def nees(errors: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """Return e^T P^-1 e for errors (..., d) and covariances (..., d, d)."""
    errors = np.asarray(errors, dtype=float)
    covs = np.asarray(covs, dtype=float)
    solved = np.linalg.solve(covs, errors[..., None])[..., 0]
    return np.einsum('...i,...i->...', errors, solved)


def chi2_band(count: int, dof: int, level: float = 0.95) -> tuple[float, float]:
    """Two-sided ``level`` band of the AVERAGE of ``count`` independent chi2(dof) values."""
    if count < 1 or dof < 1:
        raise DataError(f'chi2 band needs count >= 1 and dof >= 1, got {count} and {dof}')
    tail = 0.5 * (1.0 - level)
    low, high = stats.chi2.ppf([tail, 1.0 - tail], count * dof) / count
    return float(low), float(high)


@dataclass(frozen=True)
class NeesSummary:
    """Average NEES of ``count`` independent values with ``dof`` components and its band."""

    mean: float
    band: tuple[float, float]
    count: int
    dof: int
    inside_95: float   # share of individual values below chi2.ppf(0.95, dof)

    @property
    def consistent(self) -> bool:
        return self.band[0] <= self.mean <= self.band[1]

    def verdict(self) -> str:
        if self.consistent:
            return 'consistent'
        return 'over-confident' if self.mean > self.band[1] else 'conservative'


def summarize_nees(values: np.ndarray, dof: int, level: float = 0.95) -> NeesSummary:
    """Summarise independent NEES values of ``dof`` components against the chi2 band."""
    values = np.asarray(values, dtype=float).ravel()
    if values.size == 0:
        raise DataError('no NEES values to summarise')
    return NeesSummary(float(values.mean()), chi2_band(values.size, dof, level), int(values.size),
                       int(dof), float((values <= stats.chi2.ppf(0.95, dof)).mean()))


@dataclass(frozen=True)
class SegmentNees:
    """Odometry-alone errors on independent windows (start frame) with their NEES."""

    horizon_m: float
    errors: np.ndarray        # (N, 3): longitudinal, lateral (m), heading (rad)
    covs: np.ndarray          # (N, 3, 3) propagated covariance in the start frame
    path_m: np.ndarray        # (N,) ground-truth path length of each window
    nees: np.ndarray          # (N,) 3-dof NEES
    nees_position: np.ndarray  # (N,) 2-dof NEES of (x, y)

    def summary(self, level: float = 0.95) -> NeesSummary:
        return summarize_nees(self.nees, 3, level)

    def position_summary(self, level: float = 0.95) -> NeesSummary:
        return summarize_nees(self.nees_position, 2, level)


def segment_nees(drives: Sequence[Drive], source: TwistSource, noise: NoiseModel,
                 options: SegmentOptions | None = None,
                 parameters: ParameterUncertainty | None = None) -> SegmentNees:
    """NEES of odometry alone over independent windows of held-out drives (module docstring)."""
    options = options or SegmentOptions(horizon_m=2.0, short_drive='drop')
    segments = cut_segments(drives, options)
    if len(segments) == 0:
        raise DataError(f'no window of {options.horizon_m:g} m in the held-out drives; drive '
                        'further or shorten the horizon')
    n = len(segments)
    predicted = np.empty((n, 3))
    covs = np.empty((n, 3, 3))
    for i in range(n):
        wheels = held_wheels(drives[int(segments.drive[i])].wheels, options.interval)
        # The window starts on a wheel stamp or after it: hold the last sample <= t_a from t_a.
        first = int(np.searchsorted(wheels.t_ns, segments.t_a_ns[i], side='right')) - 1
        inner = wheels.between(int(segments.t_a_ns[i]) + 1, int(segments.t_b_ns[i]) - 1)
        t_ns = np.concatenate([[segments.t_a_ns[i]], inner.t_ns, [segments.t_b_ns[i]]])
        omega_l = np.concatenate([[wheels.omega_l[first]], inner.omega_l, [0.0]])
        omega_r = np.concatenate([[wheels.omega_r[first]], inner.omega_r, [0.0]])
        predicted[i], cov = predict(segments.start[i], np.zeros((3, 3)), t_ns, omega_l,
                                    omega_r, source, noise, parameters=parameters,
                                    interval='starting')
        cos_a, sin_a = np.cos(segments.start[i, 2]), np.sin(segments.start[i, 2])
        to_start = np.array([[cos_a, sin_a, 0.0], [-sin_a, cos_a, 0.0], [0.0, 0.0, 1.0]])
        covs[i] = to_start @ cov @ to_start.T + MIN_VARIANCE * np.eye(3)
    errors = segment_frame_error(segments.start, segments.end, predicted)
    return SegmentNees(float(options.horizon_m), errors, covs, segments.path_m.copy(),
                       nees(errors, covs), nees(errors[:, :2], covs[:, :2, :2]))


@dataclass(frozen=True)
class NeesOverTime:
    """Run-averaged NEES at each time step of M aligned runs, with the band for M runs."""

    t_s: np.ndarray
    mean: np.ndarray
    band: tuple[float, float]
    runs: int
    dof: int

    @property
    def share_inside(self) -> float:
        """Return the share of time steps whose run-average lies inside the band."""
        inside = (self.mean >= self.band[0]) & (self.mean <= self.band[1])
        return float(inside.mean()) if self.mean.size else float('nan')

    @property
    def time_average(self) -> float:
        return float(self.mean.mean()) if self.mean.size else float('nan')


def nees_over_time(t_s: np.ndarray, errors: np.ndarray, covs: np.ndarray,
                   level: float = 0.95) -> NeesOverTime:
    """Average over M runs the NEES of errors (M, K, d) with covariances (M, K, d, d)."""
    errors = np.asarray(errors, dtype=float)
    if errors.ndim != 3:
        raise DataError(f'errors must be (runs, steps, dof), got shape {errors.shape}')
    values = nees(errors, covs)
    runs, _, dof = errors.shape
    return NeesOverTime(np.asarray(t_s, dtype=float), values.mean(axis=0),
                        chi2_band(runs, dof, level), runs, dof)


@dataclass(frozen=True)
class DriveNees:
    """Odometry alone over whole drives: NEES against the distance from the start.

    ``nees`` (M, D): drive m at distance d (NaN where a drive is shorter); ``checkpoints``: the
    NEES at every ``checkpoint_s`` of every drive, with their distance from the start.
    """

    distances_m: np.ndarray
    nees: np.ndarray
    checkpoint_s: float
    checkpoint_nees: np.ndarray
    checkpoint_distance_m: np.ndarray
    drive_length_m: np.ndarray

    def summaries(self) -> dict[float, NeesSummary]:
        """Return the average over the drives at every distance, against the band for M runs."""
        out = {}
        for j, distance in enumerate(self.distances_m):
            values = self.nees[:, j]
            values = values[np.isfinite(values)]
            if values.size:
                out[float(distance)] = summarize_nees(values, 3)
        return out

    def checkpoint_summary(self) -> NeesSummary:
        return summarize_nees(self.checkpoint_nees, 3)


def drive_nees(drives: Sequence[Drive], source: TwistSource, noise: NoiseModel,
               distances_m: Sequence[float], checkpoint_s: float = 15.0,
               parameters: ParameterUncertainty | None = None,
               interval: str = DEFAULT_INTERVAL) -> DriveNees:
    """NEES of odometry alone from the start of every drive (module docstring).

    ``interval``: the sample-interval convention the odometry runs under.
    """
    if not drives:
        raise DataError('no drive to score')
    distances = np.asarray(sorted({float(d) for d in distances_m}), dtype=float)
    table = np.full((len(drives), distances.size), np.nan)
    check_nees, check_dist, lengths = [], [], []
    for m, drive in enumerate(drives):
        wheels = drive.wheels
        truth = drive.truth.interpolate(wheels.t_ns)
        poses, covs = predict_track(truth[0], np.zeros((3, 3)), wheels.t_ns, wheels.omega_l,
                                    wheels.omega_r, source, noise, parameters=parameters,
                                    interval=interval)
        errors = truth - poses
        errors[:, 2] = wrap_angle(errors[:, 2])
        covs = covs + MIN_VARIANCE * np.eye(3)
        path = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(truth[:, 0]),
                                                         np.diff(truth[:, 1])))])
        lengths.append(float(path[-1]))
        for j, distance in enumerate(distances):
            i = int(np.searchsorted(path, distance))
            if i < path.size:
                table[m, j] = float(nees(errors[i], covs[i]))
        t_s = (wheels.t_ns - wheels.t_ns[0]) * 1e-9
        wanted = np.arange(checkpoint_s, t_s[-1] + 1e-9, checkpoint_s)
        idx = np.clip(np.searchsorted(t_s, wanted), 0, t_s.size - 1)
        check_nees.append(nees(errors[idx], covs[idx]))
        check_dist.append(path[idx])
    return DriveNees(distances, table, float(checkpoint_s), np.concatenate(check_nees),
                     np.concatenate(check_dist), np.asarray(lengths))
