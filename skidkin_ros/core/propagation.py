"""Uncertainty propagation through the integrator: the prediction step of a state estimator.

The pose (x, y, yaw) is advanced by the integrator's exact SE(2) step; its covariance follows the
first-order propagation of that same step:

    P' = F P F^T + G (Q_motion + Q_input) G^T

F is the Jacobian of the step with respect to the pose, G the rotation of the body-frame
increment into the world, Q_motion the calibrated process noise (``NoiseModel``: variance growing
with distance and rotation) and Q_input the wheel-speed measurement noise mapped through the
model's Jacobian with respect to the inputs. Without a calibration the node publishes fixed
diagonals instead (never zeros).

Example, for a filter author (one prediction over a batch of wheel samples)::

    from skidkin_ros.core.models import get_model
    from skidkin_ros.core.specs import Geometry
    from skidkin_ros.core.noise import NoiseModel
    from skidkin_ros.core.propagation import predict

    model = get_model('edd_symmetric').bind({'alpha': 0.9, 'b_hat': 1.1}, Geometry(0.165, 0.555))
    noise = NoiseModel(2e-4, 1e-4, 5e-4, 2e-3)
    pose, cov = predict(pose, cov, t_ns, omega_l, omega_r, model, noise)
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from skidkin_ros.core.integrator import body_increment, step_scalar, TwistSource
from skidkin_ros.core.noise import NoiseModel

__all__ = [
    'INITIAL_VARIANCE',
    'TWIST_VARIANCE_FLOOR',
    'step_jacobians',
    'increment_input_jacobian',
    'propagate_step',
    'predict',
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

    P' = F P F^T + G Q G^T (see :func:`step_jacobians`), written out on plain floats: F differs
    from the identity in its last column only and G is a rotation, so the products are a few
    dozen multiplications; numpy's 3 x 3 products would cost more in overhead than in arithmetic,
    and this step runs once per wheel sample in the node.
    """
    x, y, yaw = (float(v) for v in pose)
    vx, vy, w = (float(v) for v in twist)
    new_x, new_y, new_yaw, dx, dy = step_scalar(x, y, yaw, vx, vy, w, dt_s)
    dth = w * dt_s
    q00 = q01 = q02 = q11 = q12 = q22 = 0.0
    if noise is not None:
        q00, q11, q22 = noise.step_variances(math.hypot(dx, dy), dth)
    if input_jacobian is not None and input_variance > 0.0:
        extra = input_variance * input_jacobian @ input_jacobian.T
        (e00, e01, e02), (_, e11, e12), (_, _, e22) = extra.tolist()
        q00, q01, q02, q11, q12, q22 = (q00 + e00, q01 + e01, q02 + e02, q11 + e11,
                                        q12 + e12, q22 + e22)
    (p00, p01, p02), (p10, p11, p12), (p20, p21, p22) = cov.tolist()
    # Symmetrize the input as the matrix form did its output.
    p01 = 0.5 * (p01 + p10)
    p02 = 0.5 * (p02 + p20)
    p12 = 0.5 * (p12 + p21)
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
    c01 = m01 + n01
    c02 = r02 + n02
    c12 = r12 + n12
    new_cov = np.array([[m00 + n00, c01, c02],
                        [c01, m11 + n11, c12],
                        [c02, c12, p22 + q22]])
    return np.array((new_x, new_y, new_yaw)), new_cov


def predict(pose: Sequence[float], cov: np.ndarray, t_ns: Sequence[int],
            omega_l: Sequence[float], omega_r: Sequence[float], source: TwistSource,
            noise: NoiseModel | None, input_variance: float = 0.0
            ) -> tuple[np.ndarray, np.ndarray]:
    """Predict the pose and its covariance from t_ns[0] to t_ns[-1].

    ``pose`` (x, y, yaw) and ``cov`` (3 x 3) hold at t_ns[0]; the wheel speeds of each sample are
    held until the next one (the integrator's zero-order hold), so the last sample only sets the
    end time. ``input_variance`` is the wheel-speed measurement variance (rad^2/s^2), propagated
    through the model's Jacobian with respect to the inputs.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    wl = np.asarray(omega_l, dtype=float)
    wr = np.asarray(omega_r, dtype=float)
    state = np.asarray(pose, dtype=float).copy()
    covariance = np.asarray(cov, dtype=float).copy()
    for i in range(len(t) - 1):
        dt_s = (t[i + 1] - t[i]) * 1e-9
        if dt_s <= 0.0:
            continue
        twist = np.asarray(source.twist(wl[i], wr[i]), dtype=float)
        jac_in = (increment_input_jacobian(source, wl[i], wr[i], dt_s)
                  if input_variance > 0.0 else None)
        state, covariance = propagate_step(state, covariance, twist, dt_s, noise, jac_in,
                                           input_variance)
    return state, covariance


def to_6x6(cov3: np.ndarray, unobserved: float = UNOBSERVED_VARIANCE) -> np.ndarray:
    """Embed a planar (x, y, yaw) covariance into ROS's 6x6 (x, y, z, roll, pitch, yaw) layout."""
    (a, b, c), (d, e, f), (g, h, i) = np.asarray(cov3, dtype=float).tolist()
    u = unobserved
    return np.array([a, b, 0.0, 0.0, 0.0, c,
                     d, e, 0.0, 0.0, 0.0, f,
                     0.0, 0.0, u, 0.0, 0.0, 0.0,
                     0.0, 0.0, 0.0, u, 0.0, 0.0,
                     0.0, 0.0, 0.0, 0.0, u, 0.0,
                     g, h, 0.0, 0.0, 0.0, i]).reshape(6, 6)


def _diagonal_6x6(values: Sequence[float]) -> np.ndarray:
    """Return a 6x6 diagonal matrix (a list-built array: cheaper than np.diag per message)."""
    flat = [0.0] * 36
    flat[::7] = values
    return np.array(flat).reshape(6, 6)


class PoseCovariancePropagator:
    """Streaming covariance for the node: call :meth:`step` for every integrated sample.

    With a calibrated ``noise`` the pose covariance grows with the motion as propagated and the
    twist covariance follows the rate model; without one, the fixed fallback diagonals are
    published.
    """

    def __init__(self, noise: NoiseModel | None, fallback_pose_diag: Sequence[float],
                 fallback_twist_diag: Sequence[float]) -> None:
        self.noise = noise
        self.fallback_pose = np.diag(np.asarray(fallback_pose_diag, dtype=float))
        self.fallback_twist = np.diag(np.asarray(fallback_twist_diag, dtype=float))
        self.cov = np.eye(3) * INITIAL_VARIANCE

    @property
    def calibrated(self) -> bool:
        return self.noise is not None

    def reset(self) -> None:
        self.cov = np.eye(3) * INITIAL_VARIANCE

    def step(self, pose_before: np.ndarray, twist: np.ndarray, dt_s: float) -> None:
        if self.noise is None:
            return
        _, self.cov = propagate_step(np.asarray(pose_before, dtype=float), self.cov,
                                     np.asarray(twist, dtype=float), dt_s, self.noise)

    def pose_covariance_6x6(self) -> np.ndarray:
        if self.noise is None:
            return self.fallback_pose.copy()
        return to_6x6(self.cov)

    def twist_covariance_6x6(self, twist: np.ndarray, period_s: float) -> np.ndarray:
        if self.noise is None or period_s <= 0.0:
            return self.fallback_twist.copy()
        speed = math.hypot(twist[0], twist[1])
        var_vx, var_vy, var_w = self.noise.twist_variances(speed, float(twist[2]), period_s)
        floor = TWIST_VARIANCE_FLOOR
        return _diagonal_6x6([max(var_vx, floor[0]), max(var_vy, floor[1]), UNOBSERVED_VARIANCE,
                              UNOBSERVED_VARIANCE, UNOBSERVED_VARIANCE, max(var_w, floor[2])])
