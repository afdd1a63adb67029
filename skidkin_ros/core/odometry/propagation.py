"""Uncertainty propagation through the integrator: the prediction step of a state estimator.

The pose (x, y, yaw) is advanced by the integrator's exact SE(2) step; its covariance follows the
first-order propagation of that same step:

    P' = F P F^T + G (Q_motion + Q_input) G^T

F is the Jacobian of the step with respect to the pose, G the rotation of the body-frame
increment into the world, Q_motion the calibrated process noise (``NoiseModel``: variance growing
with distance and rotation) and Q_input the wheel-speed measurement noise mapped through the
model's Jacobian with respect to the inputs. Without a calibration the node publishes fixed
diagonals instead (never zeros).

What is published (the node, :func:`predict`, ``skidkin predict``: one code path,
:class:`PoseCovariancePropagator`) adds two terms that are not a random walk:

    P_published = P + S Sigma_k S^T + R(yaw) C R(yaw)^T

S Sigma_k S^T is the calibration's own uncertainty (parameter covariance Sigma_k propagated
through the integrator's Jacobian with respect to the parameters,
:mod:`skidkin_ros.core.odometry.uncertainty`), C the noise model's length-independent part
(:class:`~skidkin_ros.core.odometry.noise.NoiseModel`). Both are added when the covariance is
read, never fed back into the next step.

Example, for a filter author (one prediction over a batch of wheel samples)::

    from skidkin_ros.core.kinematics.models import get_model
    from skidkin_ros.core.kinematics.specs import Geometry
    from skidkin_ros.core.odometry.noise import NoiseModel
    from skidkin_ros.core.odometry.propagation import predict

    model = get_model('edd_symmetric').bind({'alpha': 0.9, 'b_hat': 1.1}, Geometry(0.165, 0.555))
    noise = NoiseModel(2e-4, 1e-4, 5e-4, 2e-3)
    pose, cov = predict(pose, cov, t_ns, omega_l, omega_r, model, noise)
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from skidkin_ros.core.odometry.integrator import (body_increment, IntegratorLimits, SampleStatus,
                                                  step_scalar, StreamingIntegrator, TwistSource)
from skidkin_ros.core.odometry.interval import DEFAULT_INTERVAL, interval_speed
from skidkin_ros.core.odometry.noise import (FALLBACK_POSE_DIAGONAL, FALLBACK_TWIST_DIAGONAL,
                                             moving_time, NoiseModel)
from skidkin_ros.core.odometry.sensitivity import (add_weighted_outer, propagate_linear,
                                                   propagate_sensitivity)
from skidkin_ros.core.odometry.uncertainty import ParameterUncertainty

__all__ = [
    'INITIAL_VARIANCE',
    'TWIST_VARIANCE_FLOOR',
    'step_jacobians',
    'increment_input_jacobian',
    'propagate_step',
    'propagate_scalar',
    'upper_to_3x3',
    'flat_6x6',
    'predict',
    'predict_track',
    'PoseCovariancePropagator',
    'to_6x6',
]

# A freshly reset pose is exact; a tiny variance keeps the published matrix positive definite.
INITIAL_VARIANCE = 1e-9
# Lower bound on the published twist variances (m^2/s^2, m^2/s^2, rad^2/s^2): at standstill the
# rate model predicts zero, and a zero variance would make a filter trust the value blindly.
TWIST_VARIANCE_FLOOR = (1e-6, 1e-6, 1e-6)
# Variance published for the dimensions a planar model does not estimate (z, roll, pitch).
UNOBSERVED_VARIANCE = 1e6


def step_jacobians(yaw_rad: float, dx: float, dy: float) -> tuple[np.ndarray, np.ndarray]:
    """Return F (w.r.t. the pose) and G (w.r.t. the body increment) of one integrator step."""
    cos_t = np.cos(yaw_rad)
    sin_t = np.sin(yaw_rad)
    jac_pose = np.array([[1.0, 0.0, -sin_t * dx - cos_t * dy],
                         [0.0, 1.0, cos_t * dx - sin_t * dy],
                         [0.0, 0.0, 1.0]])
    jac_incr = np.array([[cos_t, -sin_t, 0.0],
                         [sin_t, cos_t, 0.0],
                         [0.0, 0.0, 1.0]])
    return jac_pose, jac_incr


def increment_input_jacobian(source: TwistSource, omega_l: float, omega_r: float,
                             dt_s: float, eps: float = 1e-6) -> np.ndarray:
    """Numerical d(dx, dy, dyaw)/d(omega_l, omega_r) of one step (3 x 2)."""
    cols = []
    for d_l, d_r in ((eps, 0.0), (0.0, eps)):
        plus = np.array(body_increment(*source.twist(omega_l + d_l, omega_r + d_r), dt_s))
        minus = np.array(body_increment(*source.twist(omega_l - d_l, omega_r - d_r), dt_s))
        cols.append((plus - minus) / (2 * eps))
    return np.stack(cols, axis=1)


def propagate_step(pose: np.ndarray, cov: np.ndarray, twist: np.ndarray, dt_s: float,
                   noise: NoiseModel | None,
                   input_jacobian: np.ndarray | None = None,
                   input_variance: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Advance (pose, cov) by one held twist over dt_s; same step as the integrator.

    P' = F P F^T + G Q G^T (see :func:`step_jacobians`); the arithmetic is
    :func:`propagate_scalar`'s.
    """
    x, y, yaw = (float(v) for v in pose)
    vx, vy, w = (float(v) for v in twist)
    upper = _upper_of(cov)  # symmetrized, as the matrix form did its output
    extra = None
    if input_jacobian is not None and input_variance > 0.0:
        (e00, e01, e02), (_, e11, e12), (_, _, e22) = (
            input_variance * input_jacobian @ input_jacobian.T).tolist()
        extra = (e00, e01, e02, e11, e12, e22)
    new_x, new_y, new_yaw, c = propagate_scalar(x, y, yaw, vx, vy, w, dt_s, upper, noise,
                                                extra)
    return np.array((new_x, new_y, new_yaw)), upper_to_3x3(c)


def upper_to_3x3(upper: Sequence[float]) -> np.ndarray:
    """Return the symmetric 3 x 3 matrix of an upper triangle (c00, c01, c02, c11, c12, c22)."""
    c00, c01, c02, c11, c12, c22 = upper
    return np.array([[c00, c01, c02], [c01, c11, c12], [c02, c12, c22]])


def propagate_scalar(x: float, y: float, yaw: float, vx: float, vy: float, w: float,
                     dt_s: float, upper: Sequence[float], noise: NoiseModel | None,
                     extra: Sequence[float] | None = None
                     ) -> tuple[float, float, float, tuple[float, ...]]:
    """:func:`propagate_step` on plain floats: returns (x', y', yaw', upper triangle of P').

    ``upper`` and the result hold (p00, p01, p02, p11, p12, p22) of the symmetric covariance;
    ``extra`` is an additional step noise in the same layout (the input noise). F differs from
    the identity in its last column only and G is a rotation, so the products are a few dozen
    multiplications; numpy's 3 x 3 products would cost more in overhead than in arithmetic,
    and this step runs once per wheel sample in the node.
    """
    return _propagate_with_increment(x, y, yaw, vx, vy, w, dt_s, upper, noise, extra)[:4]


def _propagate_with_increment(x: float, y: float, yaw: float, vx: float, vy: float, w: float,
                              dt_s: float, upper: Sequence[float], noise: NoiseModel | None,
                              extra: Sequence[float] | None = None) -> tuple:
    """:func:`propagate_scalar`, also returning the step's body-frame increment (dx, dy)."""
    new_x, new_y, new_yaw, dx, dy = step_scalar(x, y, yaw, vx, vy, w, dt_s)
    q00 = q01 = q02 = q11 = q12 = q22 = 0.0
    if noise is not None:
        q00, q11, q22 = noise.step_variances(math.hypot(dx, dy), w * dt_s,
                                             moving_time(vx, vy, w, dt_s))
    if extra is not None:
        e00, e01, e02, e11, e12, e22 = extra
        q00, q01, q02, q11, q12, q22 = (q00 + e00, q01 + e01, q02 + e02, q11 + e11,
                                        q12 + e12, q22 + e22)
    p00, p01, p02, p11, p12, p22 = upper
    cos_t = float(np.cos(yaw))
    sin_t = float(np.sin(yaw))
    a = -sin_t * dx - cos_t * dy  # F[0, 2]
    b = cos_t * dx - sin_t * dy   # F[1, 2]
    # F P F^T
    r02 = p02 + a * p22
    r12 = p12 + b * p22
    m00 = p00 + a * p02 + a * r02
    m01 = p01 + a * p12 + b * r02
    m11 = p11 + b * p12 + b * r12
    # G Q G^T, G the rotation by yaw
    g00 = cos_t * q00 - sin_t * q01
    g01 = cos_t * q01 - sin_t * q11
    g10 = sin_t * q00 + cos_t * q01
    g11 = sin_t * q01 + cos_t * q11
    n00 = g00 * cos_t - g01 * sin_t
    n01 = g00 * sin_t + g01 * cos_t
    n11 = g10 * sin_t + g11 * cos_t
    n02 = cos_t * q02 - sin_t * q12
    n12 = sin_t * q02 + cos_t * q12
    return new_x, new_y, new_yaw, (m00 + n00, m01 + n01, r02 + n02, m11 + n11, r12 + n12,
                                   p22 + q22), dx, dy


def predict(pose: Sequence[float], cov: np.ndarray, t_ns: Sequence[int],
            omega_l: Sequence[float], omega_r: Sequence[float], source: TwistSource,
            noise: NoiseModel | None, input_variance: float = 0.0,
            parameters: ParameterUncertainty | None = None,
            interval: str = DEFAULT_INTERVAL) -> tuple[np.ndarray, np.ndarray]:
    """Predict the pose and its covariance from t_ns[0] to t_ns[-1].

    ``pose`` (x, y, yaw) and ``cov`` (3 x 3) hold at t_ns[0]; the speeds between two samples are
    the sample-interval convention's (``interval``, see
    :mod:`skidkin_ros.core.odometry.interval`). The samples go through the node's streaming
    integrator, so a stateful ``source``
    (an augmented model with a lag, a time-in-drive regime) predicts what the node publishes;
    duplicate stamps update the held speeds, and samples with an older stamp or a non-finite
    speed are skipped, as in the node (there is no limit on the step length or the speed here).
    ``input_variance`` is the wheel-speed measurement variance (rad^2/s^2), propagated through
    the model's Jacobian with respect to the inputs. The covariance is the node's
    (:class:`PoseCovariancePropagator`): with ``parameters`` (the calibration's parameter
    covariance) and a noise model with a length-independent part, both are included.
    """
    poses, covs = predict_track(pose, cov, t_ns, omega_l, omega_r, source, noise, input_variance,
                                parameters, interval)
    if not len(poses):
        return np.asarray(pose, dtype=float).copy(), upper_to_3x3(_upper_of(cov))
    return poses[-1], covs[-1]


def predict_track(pose: Sequence[float], cov: np.ndarray, t_ns: Sequence[int],
                  omega_l: Sequence[float], omega_r: Sequence[float], source: TwistSource,
                  noise: NoiseModel | None, input_variance: float = 0.0,
                  parameters: ParameterUncertainty | None = None,
                  interval: str = DEFAULT_INTERVAL) -> tuple[np.ndarray, np.ndarray]:
    """:func:`predict` with the pose and published covariance after every sample.

    Returns (K, 3) poses and (K, 3, 3) covariances, K = len(t_ns); a sample that was not
    integrated repeats the previous values (the first one holds ``pose``, ``cov`` plus the
    length-independent part).
    """
    unlimited = IntegratorLimits(max_dt_s=math.inf, max_wheel_speed_rad_s=math.inf)
    integrator = StreamingIntegrator(source, unlimited, interval)
    integrator.reset(pose)
    state = np.asarray(pose, dtype=float).copy()
    propagator = PoseCovariancePropagator(noise, FALLBACK_POSE_DIAGONAL, FALLBACK_TWIST_DIAGONAL,
                                          parameters, carry_uncalibrated=True)
    propagator.reset(float(state[2]))
    propagator.cov = np.asarray(cov, dtype=float)
    count = len(t_ns)
    poses = np.empty((count, 3))
    covs = np.empty((count, 3, 3))
    current = propagator.total_cov()
    for i, (t, left, right) in enumerate(zip(np.asarray(t_ns, dtype=np.int64).tolist(),
                                             np.asarray(omega_l, dtype=float).tolist(),
                                             np.asarray(omega_r, dtype=float).tolist())):
        held = integrator.held_speeds
        result = integrator.step(t, left, right)
        if result.status is SampleStatus.INTEGRATED:
            extra = None
            if input_variance > 0.0:
                speeds = (interval_speed(held[0], left, interval),
                          interval_speed(held[1], right, interval))
                jac_in = increment_input_jacobian(source, *speeds, result.dt_s)
                extra = _upper_of(input_variance * jac_in @ jac_in.T)
            propagator.step(result.start_pose, result.step_twist, result.dt_s, extra,
                            result.step_wheels)
            state = np.asarray(result.pose)
            current = propagator.total_cov()
        poses[i] = state
        covs[i] = current
    return poses, covs


def flat_6x6(upper: Sequence[float], unobserved: float = UNOBSERVED_VARIANCE) -> list[float]:
    """Return a planar covariance in ROS's 6x6 layout, row-major, as a list of 36 floats.

    ``upper``: (c00, c01, c02, c11, c12, c22) of (x, y, yaw); the 6x6 is (x, y, z, roll, pitch,
    yaw), with ``unobserved`` on the diagonal of z, roll and pitch.
    """
    a, b, c, e, f, i = upper
    return _embed((a, b, c), (b, e, f), (c, f, i), unobserved)


def to_6x6(cov3: np.ndarray, unobserved: float = UNOBSERVED_VARIANCE) -> np.ndarray:
    """Embed a planar (x, y, yaw) covariance into ROS's 6x6 (x, y, z, roll, pitch, yaw) layout."""
    rows = np.asarray(cov3, dtype=float).tolist()
    return np.array(_embed(*rows, unobserved)).reshape(6, 6)


def _embed(row_x: Sequence[float], row_y: Sequence[float], row_yaw: Sequence[float],
           unobserved: float) -> list[float]:
    """Return the row-major 6x6 (x, y, z, roll, pitch, yaw) holding a 3 x 3 (x, y, yaw) block."""
    (a, b, c), (d, e, f), (g, h, i) = row_x, row_y, row_yaw
    u = unobserved
    return [a, b, 0.0, 0.0, 0.0, c,
            d, e, 0.0, 0.0, 0.0, f,
            0.0, 0.0, u, 0.0, 0.0, 0.0,
            0.0, 0.0, 0.0, u, 0.0, 0.0,
            0.0, 0.0, 0.0, 0.0, u, 0.0,
            g, h, 0.0, 0.0, 0.0, i]


def _diagonal_flat(values: Sequence[float]) -> list[float]:
    """Return a row-major 6x6 diagonal matrix as a list of 36 floats."""
    flat = [0.0] * 36
    flat[::7] = [float(v) for v in values]
    return flat


def _upper_of(cov3: np.ndarray) -> tuple[float, ...]:
    """Return the upper triangle of the symmetric part of a 3 x 3 matrix."""
    (p00, p01, p02), (p10, p11, p12), (p20, p21, p22) = np.asarray(cov3, dtype=float).tolist()
    return (p00, 0.5 * (p01 + p10), 0.5 * (p02 + p20), p11, 0.5 * (p12 + p21), p22)


_INITIAL_UPPER = (INITIAL_VARIANCE, 0.0, 0.0, INITIAL_VARIANCE, 0.0, INITIAL_VARIANCE)


class PoseCovariancePropagator:
    """Streaming covariance for the node: call :meth:`step` for every integrated sample.

    With a calibrated ``noise`` the pose covariance grows with the motion as propagated and the
    twist covariance follows the rate model; without one, the fixed fallback diagonals are
    published. ``parameters`` (the calibration's parameter covariance, None: not used) adds
    S Sigma_k S^T, and the noise model's length-independent part its R C R^T, to what is read
    (module docstring). The ``*_flat`` methods return row-major lists of 36 floats (what a
    message carries); the ``*_6x6`` ones the same as arrays. :attr:`cov` is the propagated
    random-walk part P alone (what a reconfiguration carries over); :meth:`total_cov` is the
    published 3 x 3.
    """

    def __init__(self, noise: NoiseModel | None, fallback_pose_diag: Sequence[float],
                 fallback_twist_diag: Sequence[float],
                 parameters: ParameterUncertainty | None = None, *,
                 carry_uncalibrated: bool = False) -> None:
        self.noise = noise
        self.carry_uncalibrated = carry_uncalibrated
        self.parameters = parameters if noise is not None else None
        self._fallback_pose = _diagonal_flat(fallback_pose_diag)
        self._fallback_twist = _diagonal_flat(fallback_twist_diag)
        self._upper = _INITIAL_UPPER
        self._yaw = 0.0
        self._sens: list[tuple[float, float, float]] = []
        # Sigma_k's eigenbasis V when S is carried as T = S V (parameters set by a learner),
        # else None (S in the parameters' own coordinates); _rows: the M (or M') a linear model
        # steps S (or T) with, () where d(twist)/dk comes from twist_jacobian or the caller.
        self._basis: np.ndarray | None = None
        self._weights: tuple[float, ...] = ()
        self._rows: tuple[tuple[float, ...], ...] = ()
        self._use(self.parameters, eigen=False)
        self.reset()

    @property
    def calibrated(self) -> bool:
        return self.noise is not None

    @property
    def cov(self) -> np.ndarray:
        """Return the propagated (x, y, yaw) covariance P, 3 x 3 (a new array)."""
        return upper_to_3x3(self._upper)

    @cov.setter
    def cov(self, value: np.ndarray) -> None:
        self._upper = _upper_of(value)

    @property
    def sensitivity(self) -> np.ndarray:
        """Return S = d pose / d k, (3, p) (empty without parameter uncertainty)."""
        carried = np.asarray(self._sens, dtype=float).reshape(-1, 3).T
        return carried if self._basis is None else carried @ self._basis.T

    def set_parameters(self, parameters: ParameterUncertainty | None) -> None:
        """Use a new parameter covariance (online calibration); the sensitivity S is kept.

        S (d pose / d k, carried since the last reset) keeps its columns when the parameters
        keep their number; otherwise it restarts from zero.
        """
        kept = self.sensitivity if self._sens else None
        self.parameters = parameters if self.noise is not None else None
        self._use(self.parameters, eigen=True)
        size = 0 if self.parameters is None else self.parameters.size
        if kept is None or kept.shape[1] != size:
            self._sens = [(0.0, 0.0, 0.0)] * size
        elif self._basis is None:
            self._sens = [tuple(column) for column in kept.T.tolist()]
        else:
            self._sens = [tuple(column) for column in (kept @ self._basis).T.tolist()]

    def _use(self, parameters: ParameterUncertainty | None, eigen: bool) -> None:
        """Choose how S is stepped and read for ``parameters`` (see __init__'s attributes).

        A linear model's S is stepped with its matrices M on floats (one fused loop); with
        ``eigen`` (parameters that change while the odometry runs: a learner's), in Sigma_k's
        eigenbasis, so the read is p outer products of 3-vectors on floats. The file's fixed
        covariance keeps S in the parameters' coordinates and its read as it was (bit for bit).
        """
        self._basis, self._weights, self._rows = None, (), ()
        if type(parameters) is not ParameterUncertainty or parameters.nonlinear is not None:
            return
        if eigen:
            self._weights, self._basis, self._rows = parameters.eigen
        else:
            self._rows = parameters.sensitivity

    def reset(self, yaw_rad: float = 0.0) -> None:
        """Restart from an exact pose with heading ``yaw_rad``."""
        self._upper = _INITIAL_UPPER
        self._yaw = float(yaw_rad)
        size = 0 if self.parameters is None else self.parameters.size
        self._sens = [(0.0, 0.0, 0.0)] * size

    def step(self, pose_before: Sequence[float], twist: Sequence[float], dt_s: float,
             extra: Sequence[float] | None = None,
             wheels: tuple[float, float] | None = None,
             jacobian: Sequence[tuple[float, float, float]] | None = None) -> None:
        """Propagate over one held step from ``pose_before`` (x, y, yaw) with ``twist``.

        ``extra``: an additional body-frame step noise, upper triangle (the input noise);
        ``wheels``: the wheel speeds integrated over the step (a model not linear in them needs
        them to carry the parameter sensitivity); ``jacobian``: d(twist)/dk of the step when the
        caller has it (a residual model's, from the state that gave the step's twist).
        """
        if self.noise is None and extra is None and not self.carry_uncalibrated:
            return  # the fallback diagonals are published: nothing to propagate
        x, y, yaw = (float(v) for v in pose_before)
        vx, vy, w = (float(v) for v in twist)
        _, _, new_yaw, self._upper, dx, dy = _propagate_with_increment(
            x, y, yaw, vx, vy, w, dt_s, self._upper, self.noise, extra)
        if self._sens:
            if jacobian is None and self._rows:
                self._sens = propagate_linear(self._sens, self._rows, yaw, w, dt_s, vx, vy,
                                              dx, dy)
                self._yaw = new_yaw
                return
            if jacobian is None:
                jacobian = self.parameters.twist_jacobian(vx, vy, w, wheels)
            if jacobian is not None:
                self._sens = propagate_sensitivity(self._sens, jacobian, yaw, vx, vy, w, dt_s)
        self._yaw = new_yaw

    def total_upper(self) -> tuple[float, ...]:
        """Return the upper triangle of the published 3 x 3: P + S Sigma_k S^T + R C R^T."""
        upper = self._upper
        if self._sens:
            if self._basis is not None:
                upper = add_weighted_outer(upper, self._sens, self._weights)
            else:
                upper = tuple(a + b for a, b in zip(upper, self.parameters.pose_covariance(
                    self._sens)))
        if self.noise is not None and self.noise.has_constant:
            upper = tuple(a + b for a, b in zip(upper, self.noise.constant_upper(self._yaw)))
        return upper

    def total_cov(self) -> np.ndarray:
        """Return the published planar (x, y, yaw) covariance, 3 x 3."""
        return upper_to_3x3(self.total_upper())

    def pose_covariance_flat(self) -> list[float]:
        if self.noise is None:
            return list(self._fallback_pose)
        return flat_6x6(self.total_upper())

    def twist_covariance_flat(self, twist: Sequence[float], period_s: float) -> list[float]:
        if self.noise is None or period_s <= 0.0:
            return list(self._fallback_twist)
        vx, vy, w = twist
        var_vx, var_vy, var_w = self.noise.twist_variances(
            math.hypot(vx, vy), float(w), period_s,
            moving_time(float(vx), float(vy), float(w), 1.0) > 0.0)
        floor = TWIST_VARIANCE_FLOOR
        return _diagonal_flat([max(var_vx, floor[0]), max(var_vy, floor[1]),
                               UNOBSERVED_VARIANCE, UNOBSERVED_VARIANCE, UNOBSERVED_VARIANCE,
                               max(var_w, floor[2])])

    def pose_covariance_6x6(self) -> np.ndarray:
        return np.array(self.pose_covariance_flat()).reshape(6, 6)

    def twist_covariance_6x6(self, twist: Sequence[float], period_s: float) -> np.ndarray:
        return np.array(self.twist_covariance_flat(twist, period_s)).reshape(6, 6)
