"""Cut drives into segments and build the padded arrays the batch integrator runs on.

A segment is a stretch [t_a, t_b] of one drive between two ground-truth poses. Segments are cut
on the ground-truth path (travelled distance ``horizon_m``, as in Baril et al. 2020), never on a
model's prediction, so every model is fitted and scored on exactly the same segments.

Cutting rule (per drive, on the valid ground-truth poses): a segment starts on a pose and ends on
the first later pose whose cumulative path length is at least ``horizon_m`` further (or, when
``horizon_rad`` is set, whose heading differs by at least that much: spins in place then still make
segments); the next segment starts where the previous ended, so segments never overlap. The
remainder at the end of a drive, shorter than the horizon, is discarded, except that a drive with
no full segment at all becomes one segment from its first to its last pose when
``short_drive='whole'`` (default). This is what windowed recordings need: the DRIVE Husky table is
made of independent 2 s windows, most of them shorter than 2 m, and each becomes one segment.
``horizon_s`` cuts by time instead of distance (the temporal horizon of Mandow 2007).

Dropped segments are counted: no motion (C13: path below ``min_motion_m`` and rotation below
``min_rotation_rad``: no information, and would bias scale factors), touching an invalid
ground-truth pose, spanning a wheel-data gap longer than ``max_gap_s``, or starting before the
first wheel sample.

:func:`usable_segments` is how a fit asks for segments: it cuts them, or raises a DataError that
names what is missing (no drive, or how many segments were dropped and why).

Padded arrays: for each segment, the wheel speeds held over [t_a, t_b] (the speeds the
sample-interval convention ``interval`` gives between two stamps,
:func:`~skidkin_ros.core.odometry.interval.held_wheels`; at t_a, those of the interval that holds
it), the step durations between t_a, the
wheel stamps strictly inside (t_a, t_b) and t_b, padded with dt = 0 to a common length.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import math
from typing import Sequence

import numpy as np

from skidkin_ros.core.drive import Drive, WheelSamples
from skidkin_ros.core.odometry.interval import check_interval, DEFAULT_INTERVAL, held_wheels
from skidkin_ros.core.odometry.se2 import wrap_angle
from skidkin_ros.core.timeunits import s_to_ns
from skidkin_ros.errors import DataError, ParameterError

__all__ = ['SegmentOptions', 'HorizonOptions', 'SegmentCounts', 'SegmentSet', 'cut_segments',
           'usable_segments', 'segment_frame_error']

SHORT_DRIVE_MODES = ('whole', 'drop')


@dataclass(frozen=True)
class SegmentOptions:
    """How drives are cut into segments (see the module docstring)."""

    horizon_m: float = 2.0
    horizon_s: float | None = None
    horizon_rad: float | None = None
    short_drive: str = 'whole'
    min_motion_m: float = 0.05
    min_rotation_rad: float = 0.05
    max_gap_s: float = 0.5
    interval: str = DEFAULT_INTERVAL

    def __post_init__(self) -> None:
        check_interval(self.interval)
        if self.horizon_s is None and not (math.isfinite(self.horizon_m) and self.horizon_m > 0):
            raise ParameterError(f'segment horizon_m must be > 0 m, got {self.horizon_m!r}')
        if self.horizon_s is not None and not self.horizon_s > 0:
            raise ParameterError(f'segment horizon_s must be > 0 s, got {self.horizon_s!r}')
        if self.horizon_rad is not None and not self.horizon_rad > 0:
            raise ParameterError(f'segment horizon_rad must be > 0 rad, got {self.horizon_rad!r}')
        if self.short_drive not in SHORT_DRIVE_MODES:
            raise ParameterError(f'short_drive must be one of {SHORT_DRIVE_MODES}, '
                                 f'got {self.short_drive!r}')

    def ends(self, start_path_m: float, path_m: float, rotation_rad: float,
             elapsed_ns: int) -> bool:
        """Tell whether a segment started at cumulative path ``start_path_m`` ends at a pose.

        The cutting rule of :func:`cut_segments` for one pose at a time (online calibration cuts
        a reference stream as it arrives): ``horizon_s`` decides alone when set, else the
        cumulative path ``path_m`` reaching ``start_path_m + horizon_m``; with ``horizon_rad``,
        turning that much since the start ends it too (the same comparisons as the batch cut).
        """
        if self.horizon_s is not None:
            return elapsed_ns >= s_to_ns(self.horizon_s) - 1
        if path_m >= start_path_m + self.horizon_m:
            return True
        return self.horizon_rad is not None and abs(rotation_rad) >= self.horizon_rad

    def too_still(self, path_m: float, rotation_rad: float) -> bool:
        """Tell whether a segment moved too little to say anything (C13's rule)."""
        return path_m < self.min_motion_m and abs(rotation_rad) < self.min_rotation_rad


@dataclass(frozen=True)
class HorizonOptions:
    """How training (h_t) and evaluation (h_e) segments are cut: shared by calibrate and diagnose.

    Training segments also end after ``h_t_rad`` of turning (spins in place still make segments);
    evaluation segments are cut by distance only, as in the paper. ``sigma_diag`` is the loss
    covariance of the end-pose errors (x [m^2], y [m^2], yaw [rad^2]).
    """

    h_t: float = 2.0
    h_e: float = 2.0
    h_t_rad: float | None = 1.0
    short_drive: str = 'whole'
    min_motion_m: float = 0.05
    min_rotation_rad: float = 0.05
    max_gap_s: float = 0.5
    min_eval_path_m: float = 0.1
    sigma_diag: tuple[float, float, float] = (1.0, 1.0, 1.0)
    interval: str = DEFAULT_INTERVAL

    def train_segments(self) -> SegmentOptions:
        return SegmentOptions(horizon_m=self.h_t, horizon_rad=self.h_t_rad,
                              short_drive=self.short_drive, min_motion_m=self.min_motion_m,
                              min_rotation_rad=self.min_rotation_rad, max_gap_s=self.max_gap_s,
                              interval=self.interval)

    def eval_segments(self) -> SegmentOptions:
        return SegmentOptions(horizon_m=self.h_e, short_drive=self.short_drive,
                              min_motion_m=self.min_motion_m,
                              min_rotation_rad=self.min_rotation_rad, max_gap_s=self.max_gap_s,
                              interval=self.interval)


@dataclass(frozen=True)
class SegmentCounts:
    """How many candidate segments were kept and why the others were dropped."""

    kept: int = 0
    stationary: int = 0
    invalid_truth: int = 0
    wheel_gap: int = 0
    no_wheel_data: int = 0
    drives_without_truth: int = 0
    whole_drive: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class SegmentSet:
    """N segments as arrays; per-step arrays are padded to L steps with dt = 0.

    start/end: (N, 3) ground-truth poses (x, y, yaw) at t_a and t_b; omega_l/omega_r/dt_s: (N, L)
    held wheel speeds (rad/s) and step durations (s); path_m: ground-truth path length; drive:
    index of the source drive in the list given to :func:`cut_segments`.
    """

    drive: np.ndarray
    t_a_ns: np.ndarray
    t_b_ns: np.ndarray
    start: np.ndarray
    end: np.ndarray
    omega_l: np.ndarray
    omega_r: np.ndarray
    dt_s: np.ndarray
    path_m: np.ndarray
    counts: SegmentCounts = field(default_factory=SegmentCounts)
    drive_names: tuple[str, ...] = ()

    def __len__(self) -> int:
        return int(self.drive.size)

    @property
    def duration_s(self) -> np.ndarray:
        return (self.t_b_ns - self.t_a_ns) * 1e-9

    @property
    def rotation_rad(self) -> np.ndarray:
        """Ground-truth heading change over each segment (unwrapped yaw difference)."""
        return self.end[:, 2] - self.start[:, 2]

    def mean_wheel_speeds(self) -> tuple[np.ndarray, np.ndarray]:
        """Time-averaged left and right wheel speeds (rad/s) of each segment."""
        total = np.maximum(self.dt_s.sum(axis=1), 1e-12)
        return ((self.omega_l * self.dt_s).sum(axis=1) / total,
                (self.omega_r * self.dt_s).sum(axis=1) / total)

    @property
    def step_counts(self) -> np.ndarray:
        """Return the number of real (unpadded) steps of each segment."""
        return (self.dt_s > 0).sum(axis=1) if self.dt_s.size else np.zeros(len(self), int)

    def batches(self, growth: float = 1.5) -> list[tuple[np.ndarray, int]]:
        """Group segments of similar step counts: (indices, width) pairs to roll out together.

        Padding every segment to the longest one wastes most of the work when a few segments are
        long (slow driving); widths grow geometrically so the waste stays below ``growth``.
        Computed once per set and growth (a fit rolls the same set out hundreds of times).
        """
        cache = self.__dict__.setdefault('_batches', {})
        if growth not in cache:
            cache[growth] = self._group(growth)
        return cache[growth]

    def _group(self, growth: float) -> list[tuple[np.ndarray, int]]:
        counts = self.step_counts
        order = np.argsort(counts, kind='stable')
        groups = []
        start = 0
        while start < order.size:
            limit = max(int(counts[order[start]] * growth), int(counts[order[start]]) + 8)
            stop = int(np.searchsorted(counts[order], limit, side='right'))
            stop = max(stop, start + 1)
            idx = order[start:stop]
            groups.append((idx, max(int(counts[idx].max()), 1)))
            start = stop
        return groups

    def subset(self, keep) -> 'SegmentSet':
        """Return the segments selected by a boolean mask or index array (counts unchanged)."""
        keep = np.asarray(keep)
        if keep.dtype == bool:
            keep = np.nonzero(keep)[0]
        names = ('drive', 't_a_ns', 't_b_ns', 'start', 'end', 'omega_l', 'omega_r', 'dt_s',
                 'path_m')
        return replace(self, **{name: getattr(self, name)[keep] for name in names})


def segment_frame_error(start: np.ndarray, true_end: np.ndarray,
                        predicted_end: np.ndarray) -> np.ndarray:
    """End-pose error (true - predicted) in the segment's start (body) frame, yaw wrapped.

    Returns (N, 3): longitudinal, lateral (m) and heading (rad) error.
    """
    dx = true_end[:, 0] - predicted_end[:, 0]
    dy = true_end[:, 1] - predicted_end[:, 1]
    cos_a = np.cos(start[:, 2])
    sin_a = np.sin(start[:, 2])
    dyaw = wrap_angle(true_end[:, 2] - predicted_end[:, 2])
    return np.stack([cos_a * dx + sin_a * dy, -sin_a * dx + cos_a * dy, dyaw], axis=-1)


def _cut_indices(path: np.ndarray, yaw: np.ndarray, t_ns: np.ndarray,
                 options: SegmentOptions) -> list[tuple[int, int]]:
    """Non-overlapping (a, b) index pairs on one run of ground-truth poses."""
    pairs = []
    a = 0
    n = path.size
    while a < n - 1:
        # Both path and time are non-decreasing: the end is a binary search away.
        if options.horizon_s is not None:
            goal = t_ns[a] + s_to_ns(options.horizon_s) - 1
            b = int(np.searchsorted(t_ns, goal, side='left'))
        else:
            b = int(np.searchsorted(path, path[a] + options.horizon_m, side='left'))
        b = max(b, a + 1)
        if options.horizon_rad is not None:
            stop = min(b, n - 1)
            turned = np.abs(yaw[a + 1:stop + 1] - yaw[a]) >= options.horizon_rad
            hits = np.nonzero(turned)[0]
            if hits.size:
                b = a + 1 + int(hits[0])
        if b >= n:
            break
        pairs.append((a, b))
        a = b
    return pairs


def _held_steps(wheels: WheelSamples, t_a: int, t_b: int) -> tuple[np.ndarray, ...] | None:
    t = wheels.t_ns
    first = int(np.searchsorted(t, t_a, side='right')) - 1
    if first < 0:
        return None
    inner_lo = int(np.searchsorted(t, t_a, side='right'))
    inner_hi = int(np.searchsorted(t, t_b, side='left'))
    inner = np.unique(t[inner_lo:inner_hi])
    breaks = np.concatenate([[t_a], inner, [t_b]]).astype(np.int64)
    held = np.searchsorted(t, breaks[:-1], side='right') - 1
    dt_s = np.diff(breaks) * 1e-9
    return wheels.omega_l[held], wheels.omega_r[held], dt_s, t[first]


def _empty_set(counts: SegmentCounts, names: tuple[str, ...]) -> SegmentSet:
    empty = np.zeros((0,))
    return SegmentSet(np.zeros(0, dtype=int), np.zeros(0, np.int64), np.zeros(0, np.int64),
                      np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 1)), np.zeros((0, 1)),
                      np.zeros((0, 1)), empty, counts, names)


def cut_segments(drives: Sequence[Drive], options: SegmentOptions | None = None) -> SegmentSet:
    """Cut every drive into segments (see the module docstring) and pad them for the integrator.

    Raises DataError when no drive has ground truth.
    """
    options = options or SegmentOptions()
    names = tuple(drive.name for drive in drives)
    counts = dict(SegmentCounts().as_dict())
    rows = []
    for index, drive in enumerate(drives):
        truth = drive.truth
        if truth is None or len(truth) < 2 or len(drive.wheels) == 0:
            counts['drives_without_truth'] += 1
            continue
        path = truth.path_length()
        poses = truth.poses
        wheels = held_wheels(drive.wheels, options.interval)
        pairs = _cut_indices(path, truth.yaw, truth.t_ns, options)
        if not pairs and options.short_drive == 'whole':
            pairs = [(0, len(truth) - 1)]
            counts['whole_drive'] += 1
        for a, b in pairs:
            if not np.all(truth.valid[a:b + 1]):
                counts['invalid_truth'] += 1
                continue
            length = float(path[b] - path[a])
            rotation = float(truth.yaw[b] - truth.yaw[a])
            if options.too_still(length, rotation):
                counts['stationary'] += 1
                continue
            steps = _held_steps(wheels, int(truth.t_ns[a]), int(truth.t_ns[b]))
            if steps is None:
                counts['no_wheel_data'] += 1
                continue
            omega_l, omega_r, dt_s, first_sample_ns = steps
            # The speed held at t_a must itself be recent, and no step may bridge a gap.
            held_age_s = (truth.t_ns[a] - first_sample_ns) * 1e-9
            if dt_s.size == 0 or dt_s.max() > options.max_gap_s or held_age_s > options.max_gap_s:
                counts['wheel_gap'] += 1
                continue
            rows.append((index, int(truth.t_ns[a]), int(truth.t_ns[b]), poses[a],
                         poses[b], omega_l, omega_r, dt_s, length))
    counts['kept'] = len(rows)
    counts_obj = SegmentCounts(**counts)
    if counts['drives_without_truth'] == len(drives):
        raise DataError('no drive has ground truth (at least 2 poses) and wheel samples; '
                        'segments need both')
    if not rows:
        return _empty_set(counts_obj, names)
    width = max(row[7].size for row in rows)
    n = len(rows)
    omega_l = np.zeros((n, width))
    omega_r = np.zeros((n, width))
    dt_s = np.zeros((n, width))
    for i, row in enumerate(rows):
        steps = row[7].size
        omega_l[i, :steps] = row[5]
        omega_r[i, :steps] = row[6]
        dt_s[i, :steps] = row[7]
    return SegmentSet(
        drive=np.array([row[0] for row in rows]),
        t_a_ns=np.array([row[1] for row in rows], dtype=np.int64),
        t_b_ns=np.array([row[2] for row in rows], dtype=np.int64),
        start=np.array([row[3] for row in rows]),
        end=np.array([row[4] for row in rows]),
        omega_l=omega_l, omega_r=omega_r, dt_s=dt_s,
        path_m=np.array([row[8] for row in rows]),
        counts=counts_obj, drive_names=names)


def usable_segments(drives: Sequence[Drive], options: SegmentOptions, what: str,
                    minimum: int = 1, needed_by: str = 'a fit') -> SegmentSet:
    """Cut the drives into segments, or raise a DataError naming what is missing.

    ``what``: the drives' role ('training', 'evaluation'); ``minimum``: how many segments
    ``needed_by`` (a calibration, a diagnosis) needs at least.
    """
    if not drives:
        raise DataError(f'no {what} drive given')
    segments = cut_segments(drives, options)
    if len(segments) < minimum:
        horizon = (f'{options.horizon_s:g} s' if options.horizon_s is not None
                   else f'{options.horizon_m:g} m')
        raise DataError(f'{len(segments)} usable {what} segment(s) out of {len(drives)} '
                        f'drive(s) ({segments.counts.as_dict()}); {needed_by} needs at least '
                        f'{minimum}: drive further than the horizon {horizon} with ground truth')
    return segments
