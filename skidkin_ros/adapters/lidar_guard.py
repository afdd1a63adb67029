"""Which lidar ground-truth poses to trust: ICP judged by its own quality, wheels for gross errors.

Recipe (:func:`flag_poses`), first reason wins for each pose:

1. **Registration gaps** (C10, C12): the poses on either side of a skipped cloud, a frame
   interval above ``max_gap_factor`` x the median, and the first pose after a chunk seam whose
   overlap test failed (lidar_chunks).
2. **Physics** (C12): an increment faster than ``max_speed_m_s`` or ``max_yaw_rate_rad_s``, a
   pose tilted beyond ``max_tilt_rad`` (ICP left the plane).
3. **ICP's own quality** (per frame, measured by the registration against the previous frame):
   too few correspondences (``min_inlier_fraction``), a residual above ``max_residual_factor``
   x the recording's median residual (how dense a scan is sets its typical residual, so the
   recording is its own reference), or a degenerate geometry (``min_degeneracy``: the planar
   position is not observable, e.g. an open field or a featureless corridor).
4. **The IMU's yaw rate** (when the recording has an IMU; the gyro does not slip): the ICP yaw
   increment over the last ``window_s`` against the gyro's integral over the same interval
   (the node's sample rules, :func:`~skidkin_ros.core.odometry.gyro.usable_gyro`, and its
   piecewise-linear :class:`~skidkin_ros.core.odometry.gyro.GyroIntegral`; an interval only
   needs to lie inside the gyro's samples: the node's gap rule is not applied here), after removing
   the gyro bias (the median difference rate); flagged beyond ``imu_abs_rad`` + ``imu_rel`` x
   the turn.
5. **Wheels, gross errors only** (C11): the wheels' forward travel (the sum of the two wheel
   angles) over ``window_s``, scaled to metres by a robust fit against ICP itself (the median
   ratio over the moving windows), is compared with ICP's forward increment; flagged beyond
   ``wheel_abs_m`` + ``wheel_rel`` x the travel, that is only when wheels and ICP disagree by
   about as much as the motion itself (ICP frozen while the wheels drive, or the reverse).
   Without an IMU, the yaw increment is checked the same way against the wheel-speed
   difference. The scale fit makes the check independent of the robot's geometry: it needs
   neither the wheel radius nor the track width, and skid or slip (the very effects a
   calibration or a diagnosis is after) stay far below its limits.

Why not the wheels first, as before: ideal wheel odometry disagrees with the truth wherever the
robot skids or slips, so a wheel check tight enough to catch ICP errors throws away the frames
where wheels and body disagree most, which are the ones the calibration and the diagnosis need.

A flagged pose is invalid: segments touching it are excluded downstream. :class:`Exclusions`
says how many poses each reason took, and how much time and path they cover.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from skidkin_ros.core.drive import ImuSamples, WheelSamples
from skidkin_ros.core.odometry.gyro_buffer import GyroIntegral, usable_gyro
from skidkin_ros.core.timeunits import s_to_ns
from skidkin_ros.errors import ParameterError

__all__ = ['GUARD_CODES', 'Exclusions', 'GuardLimits', 'flag_poses']

GUARD_CODES: dict[str, str] = {
    'after_skip': 'first pose after a skipped frame: invalid (C10)',
    'before_skip': 'last pose before a skipped frame: invalid (C10)',
    'gap': 'frame interval above max_gap_factor x the median: a frame was dropped (C12)',
    'seam': 'first pose after a chunk seam whose overlap test failed, or a failed chunk',
    'speed': 'ICP increment faster than max_speed_m_s (C12)',
    'yaw_rate': 'ICP increment turns faster than max_yaw_rate_rad_s (C12)',
    'tilt': 'roll or pitch beyond max_tilt_rad: ICP left the plane (C12)',
    'icp_inliers': 'too few correspondences with the previous frame (ICP quality)',
    'icp_residual': 'residual several times the recording median (ICP quality)',
    'icp_degenerate': 'geometry does not constrain the planar motion (ICP quality)',
    'imu_yaw': "ICP yaw increment disagrees with the IMU's yaw rate",
    'wheel_gross': 'ICP increment disagrees grossly with the wheels (C11)',
}
# Moving windows needed to fit the wheels' scale against ICP; fewer: no wheel check.
_MIN_WHEEL_WINDOWS = 20


@dataclass(frozen=True)
class GuardLimits:
    """Plausibility limits of the ground truth (units in the names); see the module docstring.

    The defaults were set on simulated drives (test/test_lidar_guard.py): correct ICP on the
    forest and courtyard scenes passes them, a frozen or jumped ICP does not.
    """

    max_speed_m_s: float = 3.0
    max_yaw_rate_rad_s: float = 3.0
    max_tilt_rad: float = 0.2
    max_gap_factor: float = 1.5
    min_inlier_fraction: float = 0.5
    max_residual_factor: float = 3.0
    min_degeneracy: float = 0.05
    window_s: float = 1.0
    imu_abs_rad: float = 0.05
    imu_rel: float = 0.1
    wheel_abs_m: float = 0.3
    wheel_rel: float = 0.5
    wheel_abs_rad: float = 0.2
    wheel_rel_yaw: float = 0.5

    def __post_init__(self) -> None:
        for name in ('max_speed_m_s', 'max_yaw_rate_rad_s', 'max_tilt_rad', 'window_s',
                     'imu_abs_rad', 'wheel_abs_m', 'wheel_abs_rad'):
            if not getattr(self, name) > 0.0:
                raise ParameterError(f'GuardLimits.{name} must be > 0, got {getattr(self, name)}')
        for name in ('min_inlier_fraction', 'max_residual_factor', 'min_degeneracy', 'imu_rel',
                     'wheel_rel', 'wheel_rel_yaw'):
            if not getattr(self, name) >= 0.0:
                raise ParameterError(f'GuardLimits.{name} must be >= 0, got '
                                     f'{getattr(self, name)}')
        if self.max_gap_factor <= 1.0:
            raise ParameterError('GuardLimits.max_gap_factor must be > 1 (a multiple of the '
                                 'median frame interval)')


@dataclass
class Exclusions:
    """What the guard excluded: poses per reason, and the checks it could and could not run."""

    poses: int = 0
    by_reason: dict[str, int] = field(default_factory=dict)
    seconds_excluded: float = 0.0
    checks: dict[str, str] = field(default_factory=dict)

    @property
    def invalid(self) -> int:
        return int(sum(self.by_reason.values()))

    def as_dict(self) -> dict[str, Any]:
        return {'poses': self.poses, 'invalid': self.invalid, 'by_reason': dict(self.by_reason),
                'seconds_excluded': self.seconds_excluded, 'checks': dict(self.checks)}

    def summary(self) -> str:
        """One line for the user: how much was excluded and why."""
        if not self.invalid:
            return f'ground truth: all {self.poses} poses kept'
        share = 100.0 * self.invalid / max(self.poses, 1)
        ranked = sorted(self.by_reason.items(), key=lambda item: -item[1])
        reasons = ', '.join(f'{n} {code}' for code, n in ranked)
        return (f'ground truth: {self.invalid} of {self.poses} poses excluded ({share:.1f} %, '
                f'{self.seconds_excluded:.1f} s): {reasons}')


def _increments(t_ns: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
                window_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Return, per pose j, the window start k and ICP's forward and yaw increments k -> j."""
    start = np.searchsorted(t_ns, t_ns - s_to_ns(window_s))
    start = np.minimum(start, np.maximum(np.arange(t_ns.size) - 1, 0))
    dx, dy = x - x[start], y - y[start]
    forward = np.cos(yaw[start]) * dx + np.sin(yaw[start]) * dy
    return start, forward, yaw - yaw[start], (t_ns - t_ns[start]) * 1e-9


def _held_integral(t_ns: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (stamps, cumulative integral) of a zero-order-held signal, for np.interp."""
    dt = np.diff(t_ns) * 1e-9
    return t_ns, np.concatenate([[0.0], np.cumsum(values[:-1] * dt)])


def _between(signal: tuple[np.ndarray, np.ndarray], t0_ns: np.ndarray,
             t1_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (integral over [t0, t1], covered) of a held signal's cumulative integral."""
    stamps, cumulative = signal
    covered = (t0_ns >= stamps[0]) & (t1_ns <= stamps[-1])
    total = np.interp(t1_ns, stamps, cumulative) - np.interp(t0_ns, stamps, cumulative)
    return total, covered


def _robust_scale(numerator: np.ndarray, denominator: np.ndarray,
                  usable: np.ndarray) -> float | None:
    """Return the median ratio over the usable windows with the larger half of |denominator|."""
    mask = usable & (np.abs(denominator) > 1e-9)
    if np.count_nonzero(mask) < _MIN_WHEEL_WINDOWS:
        return None
    mask &= np.abs(denominator) >= np.median(np.abs(denominator[mask]))
    if np.count_nonzero(mask) < _MIN_WHEEL_WINDOWS // 2:
        return None
    return float(np.median(numerator[mask] / denominator[mask]))


def flag_poses(t_ns: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
               tilt: np.ndarray, quality: np.ndarray, pose_frame: Sequence[int],
               frame_status: Sequence[str], limits: GuardLimits, *,
               wheels: WheelSamples | None = None, imu: ImuSamples | None = None,
               seams: Sequence[int] = ()) -> tuple[list[str], Exclusions]:
    """Return the reason each pose is untrusted ('' for a valid pose) and the exclusions.

    Poses sorted by time; yaw unwrapped; ``quality`` (N, 3): inlier fraction, residual (m),
    degeneracy (NaN: not measured, not judged); ``pose_frame``: the input frame of each pose;
    ``frame_status``: every input frame's registration code; ``seams``: pose indices that
    start a chunk whose seam failed its test.
    """
    n = int(t_ns.size)
    reasons = [''] * n
    exclusions = Exclusions(poses=n)
    if n == 0:
        return reasons, exclusions

    def flag(mask: np.ndarray, code: str) -> None:
        for i in np.flatnonzero(mask):
            if not reasons[i]:
                reasons[i] = code

    index = np.arange(n)
    flag(np.isin(index, np.asarray(seams, dtype=int)), 'seam')
    _flag_gaps(t_ns, pose_frame, frame_status, limits, reasons)
    dt_s = np.diff(t_ns) * 1e-9
    step = np.hypot(np.diff(x), np.diff(y))
    turn = np.abs(np.diff(yaw))
    with np.errstate(divide='ignore', invalid='ignore'):
        fast = np.concatenate([[False], (dt_s > 0) & (step / dt_s > limits.max_speed_m_s)])
        spin = np.concatenate([[False],
                               (dt_s > 0) & (turn / dt_s > limits.max_yaw_rate_rad_s)])
    flag(fast, 'speed')
    flag(spin, 'yaw_rate')
    flag(tilt > limits.max_tilt_rad, 'tilt')
    inliers, residual, degeneracy = quality[:, 0], quality[:, 1], quality[:, 2]
    with np.errstate(invalid='ignore'):
        flag(inliers < limits.min_inlier_fraction, 'icp_inliers')
        typical = np.nanmedian(residual) if np.any(np.isfinite(residual)) else np.nan
        flag(residual > limits.max_residual_factor * typical, 'icp_residual')
        flag(degeneracy < limits.min_degeneracy, 'icp_degenerate')
    own_ok = np.array([not reason for reason in reasons])
    start, forward, dyaw, span_s = _increments(t_ns, x, y, yaw, limits.window_s)
    windows_ok = own_ok & own_ok[start] & (span_s > 0)
    if imu is not None and len(imu.t_ns) >= 2:
        exclusions.checks['imu_yaw'] = _imu_check(imu, t_ns, start, dyaw, span_s, windows_ok,
                                                  limits, flag)
    else:
        exclusions.checks['imu_yaw'] = 'off: no IMU'
    if wheels is not None and len(wheels) >= 2:
        exclusions.checks['wheels'] = _wheel_check(wheels, t_ns, start, forward, dyaw,
                                                   windows_ok, imu is None, limits, flag)
    else:
        exclusions.checks['wheels'] = 'off: no wheel speeds'
    invalid = np.array([bool(reason) for reason in reasons])
    for code in GUARD_CODES:
        count = sum(1 for reason in reasons if reason == code)
        if count:
            exclusions.by_reason[code] = count
    # Time excluded: the interval before each invalid pose (what its segments would cover).
    before = np.concatenate([[0.0], dt_s])
    exclusions.seconds_excluded = float(before[invalid].sum())
    return reasons, exclusions


def _flag_gaps(t_ns: np.ndarray, pose_frame: Sequence[int], frame_status: Sequence[str],
               limits: GuardLimits, reasons: list[str]) -> None:
    skipped = np.cumsum([code in ('empty', 'tiny') for code in frame_status])
    interval = np.diff(t_ns)
    nominal_ns = float(np.median(interval)) if interval.size else 0.0
    for j in range(1, t_ns.size):
        a, b = pose_frame[j - 1], pose_frame[j]
        if b - 1 > a and skipped[b - 1] - skipped[a] > 0:
            if not reasons[j]:
                reasons[j] = 'after_skip'
            if not reasons[j - 1]:
                reasons[j - 1] = 'before_skip'
            continue
        if interval[j - 1] <= 0 or (nominal_ns > 0
                                    and interval[j - 1] > limits.max_gap_factor * nominal_ns):
            if not reasons[j]:
                reasons[j] = 'gap'


def _imu_check(imu: ImuSamples, t_ns: np.ndarray, start: np.ndarray, dyaw: np.ndarray,
               span_s: np.ndarray, usable: np.ndarray, limits: GuardLimits, flag) -> str:
    # the gyro as the node takes it: its sample rules and its piecewise-linear integral
    rate_t, rate, _ = usable_gyro(imu.t_ns, imu.yaw_rate)
    if rate_t.size < 2:
        return 'off: the IMU has fewer than 2 usable samples'
    integral = GyroIntegral(rate_t, rate)
    gyro = integral.between(t_ns[start], t_ns)
    covered = (t_ns[start] >= rate_t[0]) & (t_ns <= rate_t[-1])
    usable = usable & covered
    if np.count_nonzero(usable) < 3:
        return 'off: the IMU does not cover the lidar poses'
    with np.errstate(divide='ignore', invalid='ignore'):
        bias = float(np.median((dyaw[usable] - gyro[usable]) / span_s[usable]))
    error = np.abs(dyaw - gyro - bias * span_s)
    flag(covered & (error > limits.imu_abs_rad + limits.imu_rel * np.abs(gyro)), 'imu_yaw')
    return (f'on: yaw over {limits.window_s:g} s against the gyro (bias {bias:+.4f} rad/s '
            'removed)')


def _wheel_check(wheels: WheelSamples, t_ns: np.ndarray, start: np.ndarray,
                 forward: np.ndarray, dyaw: np.ndarray, usable: np.ndarray, yaw_too: bool,
                 limits: GuardLimits, flag) -> str:
    left = np.asarray(wheels.omega_l, dtype=float)
    right = np.asarray(wheels.omega_r, dtype=float)
    travel, covered = _between(_held_integral(wheels.t_ns, 0.5 * (left + right)), t_ns[start],
                               t_ns)
    turning, _ = _between(_held_integral(wheels.t_ns, right - left), t_ns[start], t_ns)
    scale = _robust_scale(forward, travel, usable & covered)
    if scale is None:
        return 'off: too few moving windows to scale the wheels against ICP'
    metres = scale * travel
    bad = covered & (np.abs(forward - metres) > limits.wheel_abs_m
                     + limits.wheel_rel * np.abs(metres))
    what = f'forward travel (scale {scale:.4f} m/rad fitted to ICP)'
    if yaw_too:
        yaw_scale = _robust_scale(dyaw, turning, usable & covered)
        if yaw_scale is not None:
            turn = yaw_scale * turning
            bad |= covered & (np.abs(dyaw - turn) > limits.wheel_abs_rad
                              + limits.wheel_rel_yaw * np.abs(turn))
            what += f' and yaw (scale {yaw_scale:.4f} fitted to ICP)'
    flag(bad, 'wheel_gross')
    return (f'on, gross errors only, no geometry needed: {what}; flagged beyond '
            f'{limits.wheel_abs_m:g} m + {100 * limits.wheel_rel:g} % of the travel')
