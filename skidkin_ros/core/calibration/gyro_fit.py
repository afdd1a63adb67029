"""The gyro against ground truth: its calibration, and every imu.mode scored on segments.

:func:`fit_gyro` fits ``imu.scale``, ``imu.bias`` and ``imu.time_offset`` of the measurement
model of :mod:`skidkin_ros.core.odometry.gyro`: for every pair of consecutive ground-truth poses
(a, b) of a drive, dyaw = yaw_b - yaw_a and G = the integral of the linearly interpolated gyro
over [t_a + offset, t_b + offset] satisfy dyaw = (G - bias dt) / scale, linear in (1 / scale,
bias / scale) for a fixed offset. The offset is the one with the smallest mean Huber loss of
the residuals at one fixed scale sigma (every pair counts at every offset: a pair whose residual
grows with a wrong offset cannot leave the criterion, so the criterion is V-shaped), searched on
a 25 ms grid over +-0.5 s, then 5 ms and 1 ms around the best (sigma re-estimated at the coarse
best). At that offset, iteratively trimmed least squares gives scale and bias (pairs beyond 5
robust sigma are ground-truth glitches: dropped, refit, until the kept set is stable).
Standard errors: bootstrap over blocks of at most ``BLOCK_S`` of each drive (a single drive
has standard errors too).

The gyro modes' noise, per robot (``imu.arw``, ``imu.adapt.r_floor``, ``imu.adapt.r_rel``; they
set the covariance of ``fuse`` and ``adapt`` and the filter's trust in the gyro):
:func:`gyro_white_noise` is the gyro's white noise from its own samples (the robust spread of
second differences, which cancel a smooth motion), as a density; :func:`fit_filter_noise` runs
the calibrated model in ``adapt`` through the node's odometer and fits the variance of what the
filter compares, gyro minus model yaw rate per interval, as ``r_floor + (r_rel w)^2`` by
maximum likelihood (trimmed at 5 sigma), on the drives the wheel noise is fitted on;
:func:`fit_adapt_yaw_scale` fits ``imu.adapt.yaw_noise_scale``, the share of the model's yaw
variance left in ``adapt`` (the gyro removes part of the model's heading error), by maximum
likelihood of the heading errors of ``adapt`` over the held-out segments, each run as a window
from its true start pose with a zero covariance (the gain and bias carried on).

The criterion used to be the rms of the trimmed residuals; the kept set then changes with the
offset, and ground truth whose yaw noise grows with the turning rate (kiss-icp's) lets a wrong
offset trim the turning pairs away: the demo's simulated drive fitted -405 ms for a gyro
without offset (fault matrix C100).

The odometry on windows and segments, and the score of every imu.mode
(:func:`evaluate_gyro_mode`), are in :mod:`skidkin_ros.core.calibration.gyro_windows`
(re-exported here).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from skidkin_ros.core.calibration.gyro_windows import (evaluate_gyro_mode, ModeScore,
                                                       odometry_segment_errors, predict_drives,
                                                       run_windows, segment_windows,
                                                       window_nees, window_poses)
from skidkin_ros.core.calibration.segments import SegmentSet
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.gyro_buffer import GyroIntegral, usable_gyro
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.core.parallel import fork_map, usable_cpus
from skidkin_ros.core.timeunits import s_to_ns
from skidkin_ros.errors import DataError, FitError

__all__ = ['GyroFit', 'fit_gyro', 'gyro_white_noise', 'fit_filter_noise', 'fit_adapt_yaw_scale',
           'segment_windows', 'window_poses', 'run_windows', 'window_nees', 'gyro_parameters',
           'predict_drives',
           'odometry_segment_errors', 'ModeScore', 'evaluate_gyro_mode']

TRIM_SIGMAS = 5.0
OFFSET_RANGE_S = 0.5
MIN_PAIRS = 20
MIN_ARW = 1e-6          # rad/sqrt(s): a navigation-grade gyro's white noise
MIN_WINDOWS = 10        # held-out windows for the one scale of adapt's heading noise
HUBER_K = 1.345         # the usual 95 %-efficiency tuning of the Huber loss
BLOCK_S = 10.0          # bootstrap blocks
# the offset search: (step s, half-width s) per pass; the first spans the whole range
OFFSET_PASSES = ((0.025, OFFSET_RANGE_S), (0.005, 0.025), (0.001, 0.005))
# below this share of s11 s22, the 2 x 2 normal equations' determinant has lost too many digits
NORMAL_EQUATIONS_MIN = 1e-6


@dataclass(frozen=True)
class GyroFit:
    """The gyro's calibration and how well it was determined."""

    scale: float
    bias: float
    time_offset: float
    scale_se: float
    bias_se: float
    pairs: int
    trimmed: int
    residual_rad: float        # rms of the kept residuals (per pose pair)
    period_s: float            # median gyro sample period
    at_grid_edge: bool
    # the gyro modes' noise, per robot (module docstring); NaN: not calibrated
    arw: float = float('nan')          # gyro white noise, rad/sqrt(s)
    r_floor: float = float('nan')      # adapt's measurement variance (rad/s)^2, constant part
    r_rel: float = float('nan')        # its part relative to the model's yaw rate
    r_intervals: int = 0               # covered intervals in motion it was fitted on
    adapt_yaw_scale: float = float('nan')  # imu.adapt.yaw_noise_scale
    scale_windows: int = 0             # held-out windows it was fitted on


def _pairs(drives: Sequence[Drive]) -> list[tuple]:
    """Per drive with a gyro: (GyroIntegral, t_a, t_b, dyaw) of consecutive valid poses.

    The gyro under the buffer's sample rules (:func:`usable_gyro`: what the node would use);
    a pair is kept when the gyro covers it under every searched offset (no gap longer than
    max(0.08 s, 2.5 periods), no saturated sample), so the criterion's pairs do not change
    with the offset.
    """
    out = []
    for drive in drives:
        imu, truth = drive.imu, drive.truth
        if imu is None or truth is None or len(truth) < 2 or len(imu.t_ns) < 3:
            continue
        t, g, holes = usable_gyro(imu.t_ns, imu.yaw_rate)
        if t.size < 3:
            continue
        gyro = GyroIntegral(t, g)
        max_gap = max(0.08, 2.5 * float(np.median(np.diff(t))) * 1e-9)
        ok = truth.valid[:-1] & truth.valid[1:]
        t_a, t_b = truth.t_ns[:-1][ok], truth.t_ns[1:][ok]
        dyaw = (truth.yaw[1:] - truth.yaw[:-1])[ok]
        margin = s_to_ns(OFFSET_RANGE_S)
        inside = gyro.covered(t_a - margin, t_b + margin, max_gap, holes)
        if inside.sum() == 0:
            inside = gyro.covered(t_a, t_b, max_gap, holes)
        if inside.sum():
            out.append((gyro, t_a[inside], t_b[inside], dyaw[inside]))
    return out


def _design(pairs, offset_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    off = s_to_ns(offset_s)
    big_g, dt, dyaw = [], [], []
    for gyro, t_a, t_b, dy in pairs:
        big_g.append(gyro.between(t_a + off, t_b + off))
        dt.append((t_b - t_a) * 1e-9)
        dyaw.append(dy)
    return np.concatenate(big_g), np.concatenate(dt), np.concatenate(dyaw)


def _robust_sigma(r: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


def _normal_lstsq(big_g: np.ndarray, dt: np.ndarray, dyaw: np.ndarray,
                  weight: np.ndarray | None = None) -> np.ndarray:
    """Return the (weighted) least-squares coefficients of dyaw on (G, dt): 2 x 2 normal equations.

    Ten times cheaper than ``np.linalg.lstsq`` on the (N, 2) design (the offset search and the
    bootstrap solve it hundreds of times on 10^5 pairs); the two differ by a few ulps when the
    columns are far from parallel (condition number 1.5 on the simulated 2 km: 1e-15 of the
    scale). When they are nearly parallel (G proportional to dt: a robot turning at one rate)
    the normal equations lose digits, and lstsq is used.
    """
    wg, wt = (big_g, dt) if weight is None else (weight * big_g, weight * dt)
    s11, s12, s22 = float(wg @ big_g), float(wg @ dt), float(wt @ dt)
    det = s11 * s22 - s12 * s12
    if not det > NORMAL_EQUATIONS_MIN * s11 * s22:
        root = np.ones(dyaw.size) if weight is None else np.sqrt(weight)
        design = np.stack([big_g, dt], axis=1) * root[:, None]
        return np.linalg.lstsq(design, dyaw * root, rcond=None)[0]
    b1, b2 = float(wg @ dyaw), float(wt @ dyaw)
    return np.array([(s22 * b1 - s12 * b2) / det, (s11 * b2 - s12 * b1) / det])


def _trimmed_fit(big_g: np.ndarray, dt: np.ndarray, dyaw: np.ndarray, exact: bool = True
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (coefficients, residuals, kept) of the iteratively trimmed least squares.

    ``exact`` False: solved by :func:`_normal_lstsq` (the bootstrap draws; the written scale
    and bias keep ``np.linalg.lstsq``).
    """
    design = np.stack([big_g, dt], axis=1)
    keep = np.ones(dyaw.size, dtype=bool)
    for _ in range(10):
        if exact:
            coef = np.linalg.lstsq(design[keep], dyaw[keep], rcond=None)[0]
        else:
            coef = _normal_lstsq(big_g[keep], dt[keep], dyaw[keep])
        res = dyaw - design @ coef
        sigma = max(_robust_sigma(res[keep]), 1e-12)
        new = np.abs(res) <= TRIM_SIGMAS * sigma
        if np.array_equal(new, keep) or new.sum() < 3:
            break
        keep = new
    return coef, res, keep


def _huber_fit(big_g: np.ndarray, dt: np.ndarray, dyaw: np.ndarray, sigma: float
               ) -> tuple[float, np.ndarray]:
    """Return (mean Huber loss, residuals) of the Huber fit at the fixed scale ``sigma``."""
    design = np.stack([big_g, dt], axis=1)
    weight = None
    coef = np.zeros(2)
    for _ in range(30):
        new = _normal_lstsq(big_g, dt, dyaw, weight)
        res = dyaw - design @ new
        u = np.abs(res) / (HUBER_K * sigma)
        weight = 1.0 / np.maximum(u, 1.0)
        done = np.allclose(new, coef, rtol=1e-9, atol=1e-12)
        coef = new
        if done:
            break
    u = np.abs(res) / sigma
    loss = np.where(u <= HUBER_K, 0.5 * u * u, HUBER_K * u - 0.5 * HUBER_K * HUBER_K)
    return float(np.mean(loss)), res


def _search_offset(pairs) -> float:
    """Return the time offset (s) of the smallest Huber criterion (module docstring)."""
    _, res, keep = _trimmed_fit(*_design(pairs, 0.0))
    sigma = max(_robust_sigma(res[keep]), 1e-9)
    best = 0.0
    for k, (step, half) in enumerate(OFFSET_PASSES):
        lo = max(best - half, -OFFSET_RANGE_S)
        hi = min(best + half, OFFSET_RANGE_S)
        grid = np.round(np.arange(lo, hi + 1e-9, step), 3)
        losses = [_huber_fit(*_design(pairs, float(o)), sigma)[0] for o in grid]
        best = float(grid[int(np.argmin(losses))])
        if k == 0:      # the scale of the residuals near the answer, for the finer passes
            sigma = max(_robust_sigma(_huber_fit(*_design(pairs, best), sigma)[1]), 1e-9)
    return best


def _blocks(pairs) -> list[np.ndarray]:
    """Return the pair indices (into the stacked design) of each bootstrap block."""
    out, start = [], 0
    for _, t_a, _, _ in pairs:
        label = ((t_a - t_a[0]) // s_to_ns(BLOCK_S)).astype(np.int64)
        for value in np.unique(label):
            out.append(start + np.nonzero(label == value)[0])
        start += t_a.size
    return out


def fit_gyro(drives: Sequence[Drive], bootstrap: int = 100, seed: int = 0) -> GyroFit:
    """Fit the gyro's scale, bias and time offset against the drives' ground truth.

    Raises DataError when fewer than ``MIN_PAIRS`` pose pairs have gyro samples, FitError when
    the scale is not that of a yaw-rate gyro in rad/s about +z (|scale| outside [0.5, 2]).
    """
    pairs = _pairs(drives)
    count = sum(p[1].size for p in pairs)
    if count < MIN_PAIRS:
        raise DataError(f'{count} ground-truth pose pairs have gyro samples around them; the '
                        f'gyro calibration needs at least {MIN_PAIRS}')
    offset = _search_offset(pairs)
    big_g, dt, dyaw = _design(pairs, offset)
    (a, c), res, keep = _trimmed_fit(big_g, dt, dyaw)
    if not a > 0 or not 0.5 <= 1.0 / a <= 2.0:
        scale = 1.0 / a if a != 0 else float('inf')
        raise FitError(f'the gyro yaw-rate scale fits {scale:.3g}: a yaw-rate gyro in rad/s about '
                       "the robot's +z has 1. A scale near -1: the IMU z axis points down; near "
                       '57: the rate is in deg/s. Fix the IMU driver or its frame, then '
                       'calibrate again')
    scale, bias = 1.0 / a, -c / a
    rng = np.random.default_rng(seed)
    blocks = _blocks(pairs)
    draws = []
    for _ in range(bootstrap if len(blocks) > 1 else 0):
        pick = rng.integers(0, len(blocks), len(blocks))
        idx = np.concatenate([blocks[k] for k in pick])
        (a_b, c_b), _, _ = _trimmed_fit(big_g[idx], dt[idx], dyaw[idx], exact=False)
        draws.append((1.0 / a_b, -c_b / a_b))
    se = np.std(np.array(draws), axis=0) if draws else np.array([np.nan, np.nan])
    period = float(np.median(np.concatenate([np.diff(p[0].t) for p in pairs])) * 1e-9)
    return GyroFit(float(scale), float(bias), offset, float(se[0]), float(se[1]), int(count),
                   int((~keep).sum()), float(np.sqrt(np.mean(res[keep] ** 2))), period,
                   abs(offset) >= OFFSET_RANGE_S - 0.006, gyro_white_noise(drives))


def gyro_white_noise(drives: Sequence[Drive]) -> float:
    """Return the gyro's white noise density (rad/sqrt(s)) from its samples, or NaN.

    Second differences g[k+1] - 2 g[k] + g[k-1] cancel a smooth motion and hold 6 sigma^2 of
    white noise; their robust spread (their rms when a quantised gyro makes most of them 0),
    times the square root of the sample period; at least ``MIN_ARW``.
    """
    second, periods = [], []
    for drive in drives:
        imu = drive.imu
        if imu is None or len(imu.t_ns) < 5:
            continue
        g = np.asarray(imu.yaw_rate, dtype=float)
        g = g[np.isfinite(g)]
        second.append(g[2:] - 2.0 * g[1:-1] + g[:-2])
        periods.append(np.diff(np.asarray(imu.t_ns, dtype=np.int64)) * 1e-9)
    if not second:
        return float('nan')
    d = np.concatenate(second)
    spread = 1.4826 * float(np.median(np.abs(d)))
    if spread == 0.0:
        spread = float(np.sqrt(np.mean(d * d)))
    density = spread / np.sqrt(6.0) * float(np.sqrt(np.median(np.concatenate(periods))))
    return max(density, MIN_ARW)


def fit_filter_noise(config: OdometryConfig, drives: Sequence[Drive]
                     ) -> tuple[float, float, int]:
    """Return (r_floor, r_rel, intervals): adapt's measurement noise on these drives.

    ``config`` holds the calibrated model and gyro; every covered interval in motion gives the
    filter's residual e = (gyro - learned bias) - w_mid; var(e) = r_floor + (r_rel w_mid)^2 by
    maximum likelihood, intervals beyond 5 sigma dropped and the fit repeated until stable.
    Raises DataError with fewer than ``MIN_PAIRS`` such intervals.
    """
    from scipy.optimize import minimize

    config = replace(config, values={**config.values, 'imu.mode': 'adapt'})
    odometer = Odometer.from_config(config)
    odometer.gyro.record = records = []
    for drive in drives:
        if drive.imu is not None:
            odometer.predict(drive.wheels, (0.0, 0.0, 0.0), drive.imu, covariance_at=())
    if len(records) < MIN_PAIRS:
        raise DataError(f'{len(records)} wheel intervals in motion are covered by the gyro; '
                        f"the filter's noise needs at least {MIN_PAIRS}")
    rec = np.array(records)
    e2 = (rec[:, 0] - rec[:, 1]) ** 2
    w2 = rec[:, 1] ** 2
    keep = np.ones(e2.size, dtype=bool)
    floor = 1e-10

    def nll(p, e2k, w2k):
        var = np.exp(p[0]) + np.exp(p[1]) * w2k + floor
        return float(np.sum(np.log(var) + e2k / var))

    x0 = np.array([np.log(max(float(np.median(e2)), 1e-8)), np.log(1e-2)])
    for _ in range(10):
        x0 = minimize(nll, x0, args=(e2[keep], w2[keep]), method='Nelder-Mead',
                      options={'xatol': 1e-4, 'fatol': 1e-6, 'maxiter': 2000}).x
        var = np.exp(x0[0]) + np.exp(x0[1]) * w2 + floor
        new = e2 <= TRIM_SIGMAS ** 2 * var
        if np.array_equal(new, keep) or new.sum() < MIN_PAIRS:
            break
        keep = new
    return float(np.exp(x0[0]) + floor), float(np.sqrt(np.exp(x0[1]))), int(keep.sum())


def fit_adapt_yaw_scale(config: OdometryConfig, drives: Sequence[Drive], segments: SegmentSet,
                        jobs: int = 0) -> tuple[float, int]:
    """Return (imu.adapt.yaw_noise_scale, windows) fitted on held-out ``segments`` of ``drives``.

    Each :func:`segment_windows` window is run in ``adapt``; its heading variance at the end is
    k A + B (A: the model's part, B: the gain's; two runs, k = 1 and 0); k maximises the
    likelihood of the heading errors. Raises DataError with fewer than ``MIN_WINDOWS`` windows.
    ``jobs``: processes for the two runs (0: every usable CPU; the same numbers either way).
    """
    from scipy.optimize import minimize_scalar

    windows = segment_windows(drives, segments)
    count = sum(len(w) for w in windows.values())
    if count < MIN_WINDOWS:
        raise DataError(f'{count} held-out segments start and end on wheel samples; the '
                        f"scale of adapt's heading noise needs at least {MIN_WINDOWS}")

    def heading(share: float) -> tuple[np.ndarray, np.ndarray]:
        values = {**config.values, 'imu.mode': 'adapt', 'imu.adapt.yaw_noise_scale': share}
        errors, covs, _ = run_windows(replace(config, values=values), drives, segments, windows,
                                      ends_only=True)
        return covs[:, 2, 2], errors[:, 2]

    # the two runs are independent: one per core (the same numbers either way)
    shares = (1.0, 0.0)
    runs = dict(zip(shares, fork_map(heading, shares, jobs if jobs > 0 else usable_cpus())))
    variance = {share: runs[share][0] for share in shares}
    heading_errors = {share: runs[share][1] for share in shares}
    e2 = heading_errors[1.0] ** 2  # the errors of the run at the calibrated scale 1
    b = np.maximum(variance[0.0], 1e-12)
    a = np.maximum(variance[1.0] - variance[0.0], 0.0)

    def nll(log_k: float) -> float:
        var = np.exp(log_k) * a + b
        return float(np.sum(np.log(var) + e2 / var))

    best = minimize_scalar(nll, bounds=(np.log(1e-6), np.log(100.0)), method='bounded')
    return float(np.exp(best.x)), count


def gyro_parameters(fit: GyroFit) -> dict[str, float]:
    """Return the imu.* values a gyro calibration writes (the mode stays the user's choice)."""
    noise = {}
    if np.isfinite(fit.arw) and fit.arw > 0:
        noise['imu.arw'] = float(fit.arw)
    if np.isfinite(fit.r_floor) and np.isfinite(fit.r_rel):
        noise['imu.adapt.r_floor'] = float(min(max(fit.r_floor, 1e-10), 100.0))
        noise['imu.adapt.r_rel'] = float(min(fit.r_rel, 10.0))
    if np.isfinite(fit.adapt_yaw_scale):
        noise['imu.adapt.yaw_noise_scale'] = float(fit.adapt_yaw_scale)
    return {**noise, 'imu.scale': fit.scale, 'imu.bias': fit.bias,
            'imu.time_offset': fit.time_offset,
            'imu.max_gap': round(max(0.08, 2.5 * fit.period_s), 4),
            'imu.timeout': round(max(0.2, 5.0 * fit.period_s), 4),
            # a wheel sample needs the gyro up to its stamp + offset and two samples more
            'imu.max_wait': round(min(max(0.05, fit.time_offset + 2.5 * fit.period_s), 0.5), 4),
            'imu.bias_sigma': float(max(fit.bias_se if np.isfinite(fit.bias_se) else 1e-3,
                                        1e-4))}
