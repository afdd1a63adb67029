"""Calibrate each model's NoiseModel from held-out segment residuals, and check its consistency.

Segment covariance of the rate model (skidkin_ros.core.odometry.noise): every integration step j of
a segment adds the body-frame covariance C_j = diag(q_x ds_j, q_y ds_j, q_ym ds_j + q_yr |dth_j|),
ds_j and dth_j being the length and rotation of the model's own predicted step. It is carried to
the segment end exactly as the prediction step carries it (odometry.propagation.propagate_step,
started from a zero covariance): rotated into the segment's start frame by the heading theta_j
before the step, and a heading error made at step j moves every later position through the
lever arm from the pose after step j to the segment end. With A_j = Phi_j R(theta_j),

    Phi_j = [[1, 0, -(y_end - y_j+1)], [0, 1, x_end - x_j+1], [0, 0, 1]]
    Sigma_seg = sum_j A_j C_j A_j^T

which is linear in the four rates: Sigma_seg = sum over rates of rate * basis (SegmentMotion).
The part per second of motion has the same form with the step's time in motion
(:func:`skidkin_ros.core.odometry.noise.moving_time`) in place of ds_j: C_j = diag(q_xs dt_j, 0,
q_yaws dt_j).
The length-independent part C of the noise model adds R(dth) C R(dth)^T, dth the segment's
predicted rotation (C is body-frame at the end pose, as the node adds it), and the calibration's
own uncertainty, when given, adds S Sigma_k S^T with S the sensitivity of the predicted end pose to
the parameters (a fixed term: the noise values are fitted around it). All of it is
:func:`segment_covariances`, the one function that turns noise values and a segment into its
covariance (used by this fit, its consistency check and the calibration loss).
This is the same covariance, to rounding, as ``propagation.predict`` from a zero covariance over
the segment's wheel samples, so the rates fitted here are consistent with what the node and a
filter propagate. (An earlier version accumulated the step covariances without the lever arm;
with full propagation it over-predicted the position variance by ~40 % on 2 m segments, and the
held-out NEES fell below its chi2 band.)

Fit: maximum likelihood of the start-frame errors e_i ~ N(0, Sigma_seg,i) over the nine
non-negative values (four rates, three constants, two per second; log-parameterised, L-BFGS-B
with the analytic gradient, a few starts). The calibrator fits them on held-out segments of
several horizons at once (0.5, 1, 2 and 4 m by default: a composite likelihood, the segments of
one horizon overlap those of another): one horizon cannot tell a variance per metre from a
constant, several can. The
rates alone, fitted at 2 m, gave an average NEES of 3.9 at 1 m and 2.0 at 4 m on simulated drives
(``skidkin estimate``).

Coverage: real skid errors have heavier tails than a Gaussian, so the maximum-likelihood rates
put fewer than 95 % of the errors inside the predicted 95 % region (about 90 % on the Husky data).
:func:`calibrate_noise` therefore multiplies all the values by one factor, the smallest >= 1 that
puts 95 % of the errors they were fitted on inside that region (:func:`coverage_scale`). It never
shrinks the rates: where the Gaussian model already covers (simulated noise), the factor is 1 or
close to it. The published covariance is then right where a filter's gating looks (the 95 %
region) at the price of being conservative for typical errors.

Consistency: the share of segments whose error lies inside the predicted 95 % region, using the
Mahalanobis distance on (x, y, yaw) against chi2 with 3 degrees of freedom (and, reported too,
the position-only 2-dof share). The goal is close to 95 %. To be honest about it the share is
computed two-fold: rates fitted (and scaled) on the even segments are checked on the odd ones and
vice versa.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
from scipy import optimize, stats

from skidkin_ros.core.calibration.fitting import predict_end_poses, segment_errors
from skidkin_ros.core.calibration.segments import segment_frame_error, SegmentSet
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.noise import moving_time, NoiseModel
from skidkin_ros.core.odometry.se2 import body_increment, rollout_segments
from skidkin_ros.errors import DataError

__all__ = ['SegmentMotion', 'Consistency', 'HorizonCheck', 'NoiseFit', 'segment_motion',
           'segment_covariances', 'parameter_sensitivity', 'fit_noise_model', 'coverage_scale',
           'consistency', 'calibrate_noise', 'MIN_VARIANCE', 'mahalanobis']

MIN_VARIANCE = 1e-12
CHI2_95_3DOF = float(stats.chi2.ppf(0.95, 3))
CHI2_95_2DOF = float(stats.chi2.ppf(0.95, 2))
# Fewer held-out segments than this at a horizon: its NEES band is too wide to support a claim.
MIN_CHECK_SEGMENTS = 30


@dataclass(frozen=True)
class SegmentMotion:
    """Covariance bases of N segments: Sigma_seg = sum of value * basis (+ the fixed term).

    ``basis_const`` (3, N, 3, 3): R(dth) e_j e_j^T R(dth)^T for j = x, y, yaw; ``fixed`` (N, 3, 3):
    a covariance not fitted (the parameter term S Sigma_k S^T), or None; ``basis_time``
    (2, N, 3, 3): the x and yaw bases weighted by each step's time in motion instead of its length.
    """

    basis_x: np.ndarray
    basis_y: np.ndarray
    basis_yaw_m: np.ndarray
    basis_yaw_rad: np.ndarray
    basis_const: np.ndarray | None = None
    fixed: np.ndarray | None = field(default=None, repr=False)
    basis_time: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.basis_x.shape[0])

    def stack(self) -> np.ndarray:
        """Return the (9, N, 3, 3) bases in NoiseModel field order (zeros where absent)."""
        const = (self.basis_const if self.basis_const is not None
                 else np.zeros((3,) + self.basis_x.shape))
        time = (self.basis_time if self.basis_time is not None
                else np.zeros((2,) + self.basis_x.shape))
        return np.concatenate([np.stack([self.basis_x, self.basis_y, self.basis_yaw_m,
                                         self.basis_yaw_rad]), const, time])

    def covariances(self, noise: NoiseModel) -> np.ndarray:
        values = np.array(list(noise.as_dict().values()), dtype=float)
        cov = np.einsum('r,rnij->nij', values, self.stack())
        return cov if self.fixed is None else cov + self.fixed

    def subset(self, idx: np.ndarray) -> 'SegmentMotion':
        return SegmentMotion(self.basis_x[idx], self.basis_y[idx], self.basis_yaw_m[idx],
                             self.basis_yaw_rad[idx],
                             None if self.basis_const is None else self.basis_const[:, idx],
                             None if self.fixed is None else self.fixed[idx],
                             None if self.basis_time is None else self.basis_time[:, idx])

    @staticmethod
    def concat(parts: Sequence['SegmentMotion']) -> 'SegmentMotion':
        """Join the segments of several sets (e.g. horizons) into one."""
        def join(name, axis=0):
            values = [getattr(p, name) for p in parts]
            if any(v is None for v in values):
                return None
            return np.concatenate(values, axis=axis)
        return SegmentMotion(join('basis_x'), join('basis_y'), join('basis_yaw_m'),
                             join('basis_yaw_rad'), join('basis_const', axis=1), join('fixed'),
                             join('basis_time', axis=1))


@dataclass(frozen=True)
class HorizonCheck:
    """Held-out average NEES at one horizon, with its chi2 band (3 dof)."""

    horizon_m: float
    mean_nees: float
    band: tuple[float, float]
    inside_95: float
    segments: int

    @property
    def verdict(self) -> str:
        if self.segments < MIN_CHECK_SEGMENTS:
            return 'too few segments to tell'
        if self.band[0] <= self.mean_nees <= self.band[1]:
            return 'consistent'
        return 'over-confident' if self.mean_nees > self.band[1] else 'conservative'


@dataclass(frozen=True)
class Consistency:
    """Share of held-out segment errors inside the predicted 95 % regions."""

    inside_95_3dof: float
    inside_95_position_2dof: float
    segments: int
    horizons: tuple[HorizonCheck, ...] = ()


@dataclass(frozen=True)
class NoiseFit:
    """A calibrated noise model with its consistency figure."""

    model: str
    noise: NoiseModel
    consistency: Consistency
    coverage_scale: float = 1.0  # the factor applied to the maximum-likelihood values


def parameter_sensitivity(name: str, values: Mapping[str, float], geometry: Geometry,
                          segments: SegmentSet, rel_step: float = 1e-6) -> np.ndarray:
    """Return d(predicted end pose, start frame)/dk for every segment, (N, 3, p).

    Central differences: the exact slope (:func:`~skidkin_ros.core.calibration.fitting.
    segment_errors_jacobian`) is as cheap, but the noise likelihood of a model with many
    parameters is so flat that a change of 1e-9 in this fixed term moved its values by 5 %.
    """
    model = get_model(name)
    k = model.vector(dict(values), geometry)
    out = np.zeros((len(segments), 3, k.size))
    for j in range(k.size):
        step = rel_step * max(abs(float(k[j])), 1.0)
        plus, minus = k.copy(), k.copy()
        plus[j] += step
        minus[j] -= step
        out[:, :, j] = segment_frame_error(
            segments.start, predict_end_poses(model, plus, geometry, segments),
            predict_end_poses(model, minus, geometry, segments)) / (2.0 * step)
    return out


def segment_motion(name: str, values: Mapping[str, float], geometry: Geometry,
                   segments: SegmentSet,
                   parameter_covariance: np.ndarray | None = None) -> SegmentMotion:
    """Build the covariance bases of every segment from the model's predicted steps.

    ``parameter_covariance`` (p, p): the calibration's own uncertainty, added as the fixed term.
    """
    model = get_model(name)
    k = model.vector(dict(values), geometry)
    twist = model.twist(k, geometry, segments.omega_l, segments.omega_r)
    start = np.zeros((len(segments), 3))
    poses = rollout_segments(twist, segments.dt_s, start)
    theta = poses[:, :-1, 2]
    # Chord length and rotation of each step, as propagate_step measures them (padding: 0).
    dx, dy, dth = body_increment(twist[..., 0], twist[..., 1], twist[..., 2], segments.dt_s)
    ds = np.hypot(dx, dy)
    dth = np.abs(dth)
    moving = moving_time(twist[..., 0], twist[..., 1], twist[..., 2], segments.dt_s)
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    n = len(segments)

    def planar(axis_x: float, axis_y: float, cos_a: np.ndarray, sin_a: np.ndarray,
               weight: np.ndarray) -> np.ndarray:
        # R u u^T R^T weighted and summed over steps, for the body axis u (no lever arm: a
        # position error is carried to the end unchanged).
        ux = cos_a * axis_x - sin_a * axis_y
        uy = sin_a * axis_x + cos_a * axis_y
        basis = np.zeros((n, 3, 3))
        basis[:, 0, 0] = (weight * ux * ux).reshape(n, -1).sum(axis=1)
        basis[:, 0, 1] = basis[:, 1, 0] = (weight * ux * uy).reshape(n, -1).sum(axis=1)
        basis[:, 1, 1] = (weight * uy * uy).reshape(n, -1).sum(axis=1)
        return basis

    # A heading error gained at step j moves the end by the lever arm from the pose after j.
    end = poses[:, -1:, :]
    lever = np.stack([-(end[..., 1] - poses[:, 1:, 1]), end[..., 0] - poses[:, 1:, 0],
                      np.ones_like(ds)], axis=-1)
    outer = lever[..., :, None] * lever[..., None, :]
    yaw_m = np.einsum('nl,nlij->nij', ds, outer)
    yaw_rad = np.einsum('nl,nlij->nij', dth, outer)
    time = np.stack([planar(1.0, 0.0, cos_t, sin_t, moving),
                     np.einsum('nl,nlij->nij', moving, outer)])
    # Length-independent part: body-frame C at the end pose, rotated by the segment's rotation.
    turn = poses[:, -1, 2]
    cos_e, sin_e, one = np.cos(turn), np.sin(turn), np.ones(n)
    const_yaw = np.zeros((n, 3, 3))
    const_yaw[:, 2, 2] = 1.0
    const = np.stack([planar(1.0, 0.0, cos_e, sin_e, one), planar(0.0, 1.0, cos_e, sin_e, one),
                      const_yaw])
    fixed = None
    if parameter_covariance is not None and np.any(parameter_covariance):
        sens = parameter_sensitivity(name, values, geometry, segments)
        fixed = np.einsum('nik,kl,njl->nij', sens, np.asarray(parameter_covariance, float), sens)
    return SegmentMotion(planar(1.0, 0.0, cos_t, sin_t, ds), planar(0.0, 1.0, cos_t, sin_t, ds),
                         yaw_m, yaw_rad, const, fixed, time)


def segment_covariances(noise: NoiseModel, motion: SegmentMotion) -> np.ndarray:
    """Predicted (N, 3, 3) start-frame covariance of every segment's end-pose error.

    The one function from noise values and segments to their covariance (module docstring): the
    rates, the length-independent part and the fixed parameter term.
    """
    cov = motion.covariances(noise)
    return cov + MIN_VARIANCE * np.eye(3)


def mahalanobis(cov: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """Return the squared Mahalanobis distance of each error (N, d) under its covariance."""
    return np.einsum('ni,nij,nj->n', errors, np.linalg.inv(cov), errors)


def _inverse_3x3(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the inverses and determinants of (N, 3, 3) matrices, by cofactors.

    The likelihood inverts every segment's covariance at each of its hundreds of evaluations;
    the closed form is several times cheaper than LAPACK's batched LU for 3 x 3 (same values
    to rounding). Inverses where the determinant is not > 0 are not used.
    """
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2]
    d, e, f = cov[:, 1, 0], cov[:, 1, 1], cov[:, 1, 2]
    g, h, i = cov[:, 2, 0], cov[:, 2, 1], cov[:, 2, 2]
    adj = np.empty(cov.shape)
    adj[:, 0, 0] = e * i - f * h
    adj[:, 0, 1] = c * h - b * i
    adj[:, 0, 2] = b * f - c * e
    adj[:, 1, 0] = f * g - d * i
    adj[:, 1, 1] = a * i - c * g
    adj[:, 1, 2] = c * d - a * f
    adj[:, 2, 0] = d * h - e * g
    adj[:, 2, 1] = b * g - a * h
    adj[:, 2, 2] = a * e - b * d
    det = a * adj[:, 0, 0] + b * adj[:, 1, 0] + c * adj[:, 2, 0]
    with np.errstate(divide='ignore', invalid='ignore'):
        inv = adj / det[:, None, None]
    return inv, det


def fit_noise_model(errors: np.ndarray, motion: SegmentMotion, constant: bool = True,
                    weights: np.ndarray | None = None, time: bool = True) -> NoiseModel:
    """Maximum-likelihood noise values from start-frame errors (N, 3) and their bases.

    ``constant=False`` leaves the length-independent part at zero, ``time=False`` the part per
    second of motion (both False: the four per-metre and per-radian rates of the classic model).
    ``weights`` (N,): each segment's weight in the (composite) likelihood.
    """
    if errors.shape[0] < 4:
        raise DataError(f'{errors.shape[0]} held-out segments are too few to fit the noise '
                        'model (need at least 4)')
    bases = motion.stack()
    use = np.array([True] * 4 + [constant] * 3 + [time and motion.basis_time is not None] * 2)
    mats = bases[use]
    fixed = MIN_VARIANCE * np.eye(3) + (0.0 if motion.fixed is None else motion.fixed)
    dist = max(float(motion.basis_yaw_m[:, 2, 2].mean()), 1e-9)
    turn = max(float(motion.basis_yaw_rad[:, 2, 2].mean()), 1e-9)
    pos = max(float(np.mean(errors[:, :2] ** 2)), 1e-12)
    yaw = max(float(np.mean(errors[:, 2] ** 2)), 1e-12)
    moving = max(float(bases[8][:, 2, 2].mean()), 1e-9)
    guess = np.array([pos / dist, pos / dist, yaw / dist / 2, yaw / turn / 2,
                      0.1 * pos, 0.1 * pos, 0.1 * yaw, pos / moving / 2, yaw / moving / 4])[use]

    w = np.ones(errors.shape[0]) if weights is None else np.asarray(weights, dtype=float)
    flat = np.ascontiguousarray(mats.reshape(mats.shape[0], -1))  # (r, N * 9): BLAS products

    def nll(z: np.ndarray) -> tuple[float, np.ndarray]:
        theta = np.exp(z)
        cov = (theta @ flat).reshape(-1, 3, 3) + fixed
        inv, det = _inverse_3x3(cov)
        if not np.all(det > 0):
            return 1e300, np.zeros_like(z)
        logdet = np.log(det)
        a = np.einsum('nij,nj->ni', inv, errors)
        value = 0.5 * float((w * (logdet + np.einsum('ni,ni->n', errors, a))).sum())
        # d/dtheta_r = 0.5 sum_i w_i tr((inv - a a^T) M_r,i); chain rule through exp
        outer = (inv - a[:, :, None] * a[:, None, :]) * w[:, None, None]
        # the bases are symmetric: tr(outer M) is the elementwise sum of outer * M
        grad = 0.5 * (flat @ outer.reshape(-1)) * theta
        return value, grad

    z0 = np.log(guess)
    box = [(z - 25.0, z + 12.0) for z in z0]
    best = None
    for shift in (0.0, -3.0, 2.0):
        sol = optimize.minimize(nll, z0 + shift, jac=True, method='L-BFGS-B', bounds=box,
                                options={'maxiter': 3000, 'ftol': 1e-13, 'gtol': 1e-9})
        if best is None or sol.fun < best.fun:
            best = sol
    values = np.zeros(use.size)
    values[use] = np.exp(best.x)
    # Values the likelihood drove to its floor are zero, not 1e-11 of the start.
    values[use] = np.where(best.x <= np.array([lo for lo, _ in box]) + 1e-6, 0.0, values[use])
    return NoiseModel(*(float(v) for v in values))


def consistency(noise: NoiseModel, errors: np.ndarray, motion: SegmentMotion) -> Consistency:
    """Share of errors inside the predicted 95 % region (3 dof on x, y, yaw; 2 dof position)."""
    cov = segment_covariances(noise, motion)
    maha3 = mahalanobis(cov, errors)
    pos = errors[:, :2]
    maha2 = mahalanobis(cov[:, :2, :2], pos)
    n = errors.shape[0]
    return Consistency(float((maha3 <= CHI2_95_3DOF).mean()) if n else float('nan'),
                       float((maha2 <= CHI2_95_2DOF).mean()) if n else float('nan'), n)


def coverage_scale(noise: NoiseModel, errors: np.ndarray, motion: SegmentMotion,
                   target: float = 0.95) -> float:
    """Return the smallest factor >= 1 on the noise values that puts ``target`` of the errors in.

    The region is the predicted 95 % region on (x, y, yaw). Scaling the noise values by s scales
    their part of the covariance; the fixed parameter term is not scaled, so the factor is found
    by bisection (a quantile of the Mahalanobis distances when there is no fixed term).
    """
    if errors.shape[0] == 0:
        return 1.0

    def inside(scale: float) -> float:
        cov = segment_covariances(_scaled(noise, scale), motion)
        return float((mahalanobis(cov, errors) <= CHI2_95_3DOF).mean())

    if motion.fixed is None:
        maha = mahalanobis(segment_covariances(noise, motion), errors)
        needed = float(np.quantile(maha, target, method='higher')) / CHI2_95_3DOF
        return max(1.0, needed * (1.0 + 1e-9))  # the margin keeps the bound inclusive
    if inside(1.0) >= target:
        return 1.0
    low, high = 1.0, 2.0
    while inside(high) < target and high < 1e6:
        low, high = high, 2.0 * high
    for _ in range(40):
        mid = 0.5 * (low + high)
        low, high = (low, mid) if inside(mid) >= target else (mid, high)
    return high


def _scaled(noise: NoiseModel, scale: float) -> NoiseModel:
    return NoiseModel(*(value * scale for value in noise.as_dict().values()))


def _fit_covering(sets: Sequence[tuple[np.ndarray, SegmentMotion]], constant: bool,
                  time: bool = True) -> tuple[NoiseModel, float]:
    """Fit on every horizon's (errors, motion) at once; scale to cover 95 % of the first.

    Every horizon weighs the same in the likelihood (its segments by 1 / their count): the
    same drives cut at 0.5 m give four times the segments of 2 m, and would otherwise outvote it.
    """
    errors = np.concatenate([e for e, _ in sets])
    motion = SegmentMotion.concat([m for _, m in sets])
    weights = np.concatenate([np.full(len(e), len(sets[0][0]) / max(len(e), 1))
                              for e, _ in sets])
    noise = fit_noise_model(errors, motion, constant, weights, time)
    scale = coverage_scale(noise, *sets[0])
    return _scaled(noise, scale), scale


def _horizon_check(horizon_m: float, errors: np.ndarray, cov: np.ndarray) -> HorizonCheck:
    values = mahalanobis(cov, errors)
    n = values.size
    low, high = stats.chi2.ppf([0.025, 0.975], 3 * max(n, 1)) / max(n, 1)
    return HorizonCheck(float(horizon_m), float(values.mean()) if n else float('nan'),
                        (float(low), float(high)),
                        float((values <= CHI2_95_3DOF).mean()) if n else float('nan'), int(n))


def calibrate_noise(name: str, values: Mapping[str, float], geometry: Geometry,
                    segments: SegmentSet,
                    other_horizons: Mapping[float, SegmentSet] | None = None,
                    parameter_covariance: np.ndarray | None = None,
                    horizon_m: float = 2.0, constant: bool = True,
                    time: bool = True) -> NoiseFit:
    """Fit a model's noise on held-out segments and scale it to cover 95 % of them.

    ``segments`` are cut at the calibration horizon ``horizon_m`` (coverage is counted there);
    ``other_horizons`` are the same held-out drives cut at other horizons, fitted together with
    them. ``parameter_covariance`` is the fit's own (a fixed term). The consistency is checked
    two-fold: values fitted and scaled on one half of every horizon's segments, checked on the
    other half, with the average NEES per horizon against its chi2 band.
    """
    model = get_model(name)
    k = model.vector(dict(values), geometry)
    by_horizon = {float(horizon_m): segments, **{float(h): s for h, s in
                                                 (other_horizons or {}).items()
                                                 if float(h) != float(horizon_m) and len(s)}}
    sets = {h: (segment_errors(model, k, geometry, s),
                segment_motion(name, values, geometry, s, parameter_covariance))
            for h, s in by_horizon.items()}
    ordered = [sets[float(horizon_m)]] + [v for h, v in sets.items() if h != float(horizon_m)]
    noise, scale = _fit_covering(ordered, constant, time)
    halves = {h: (np.arange(0, len(e), 2), np.arange(1, len(e), 2)) for h, (e, _) in sets.items()}
    main_even, main_odd = halves[float(horizon_m)]
    if main_even.size < 4 or main_odd.size < 4:
        return NoiseFit(name, noise, consistency(noise, *sets[float(horizon_m)]), scale)
    maha = {h: [] for h in sets}
    errs = {h: [] for h in sets}
    inside3, inside2, count = 0.0, 0.0, 0
    for fold in (0, 1):
        part_sets = [(e[halves[h][fold]], m.subset(halves[h][fold]))
                     for h, (e, m) in [(float(horizon_m), sets[float(horizon_m)])]
                     + [(h, v) for h, v in sets.items() if h != float(horizon_m)]
                     if halves[h][fold].size]
        part, _ = _fit_covering(part_sets, constant, time)
        for h, (e, m) in sets.items():
            idx = halves[h][1 - fold]
            if not idx.size:
                continue
            maha[h].append(segment_covariances(part, m.subset(idx)))
            errs[h].append(e[idx])
        main_e, main_m = sets[float(horizon_m)]
        idx = halves[float(horizon_m)][1 - fold]
        check = consistency(part, main_e[idx], main_m.subset(idx))
        inside3 += check.inside_95_3dof * check.segments
        inside2 += check.inside_95_position_2dof * check.segments
        count += check.segments
    checks = tuple(_horizon_check(h, np.concatenate(errs[h]), np.concatenate(maha[h]))
                   for h in sorted(sets) if errs[h])
    return NoiseFit(name, noise, Consistency(inside3 / count, inside2 / count, count, checks),
                    scale)
