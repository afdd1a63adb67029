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

from typing import Sequence

import numpy as np

from skidkin_ros.core.integrator import body_increment, compose, TwistSource
from skidkin_ros.core.noise import NoiseModel

__all__ = [
    'INITIAL_VARIANCE',
    'TWIST_VARIANCE_FLOOR',
    'step_jacobians',
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


def _increment_input_jacobian(source: TwistSource, omega_l: float, omega_r: float,
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
    """Advance (pose, cov) by one held twist over dt_s; same step as the integrator."""
    dx, dy, dth = body_increment(twist[0], twist[1], twist[2], dt_s)
    new_pose = np.array(compose(pose[0], pose[1], pose[2], dx, dy, dth), dtype=float)
    jac_pose, jac_incr = step_jacobians(pose[2], float(dx), float(dy))
    q_body = np.zeros((3, 3))
    if noise is not None:
        q_body = noise.step_covariance(float(np.hypot(dx, dy)), float(dth))
    if input_jacobian is not None and input_variance > 0.0:
        q_body = q_body + input_variance * input_jacobian @ input_jacobian.T
    new_cov = jac_pose @ cov @ jac_pose.T + jac_incr @ q_body @ jac_incr.T
    return new_pose, 0.5 * (new_cov + new_cov.T)


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
        jac_in = (_increment_input_jacobian(source, wl[i], wr[i], dt_s)
                  if input_variance > 0.0 else None)
        state, covariance = propagate_step(state, covariance, twist, dt_s, noise, jac_in,
                                           input_variance)
    return state, covariance


def to_6x6(cov3: np.ndarray, unobserved: float = UNOBSERVED_VARIANCE) -> np.ndarray:
    """Embed a planar (x, y, yaw) covariance into ROS's 6x6 (x, y, z, roll, pitch, yaw) layout."""
    full = np.diag([0.0, 0.0, unobserved, unobserved, unobserved, 0.0])
    idx = [0, 1, 5]
    for a, i in enumerate(idx):
        for b, j in enumerate(idx):
            full[i, j] = cov3[a, b]
    return full


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
        speed = float(np.hypot(twist[0], twist[1]))
        var_vx, var_vy, var_w = self.noise.twist_variances(speed, float(twist[2]), period_s)
        floor = TWIST_VARIANCE_FLOOR
        full = np.diag([max(var_vx, floor[0]), max(var_vy, floor[1]), UNOBSERVED_VARIANCE,
                        UNOBSERVED_VARIANCE, UNOBSERVED_VARIANCE, max(var_w, floor[2])])
        return full
