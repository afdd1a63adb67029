"""How odometry error grows with motion: the calibrated process noise.

The error of an odometry model over a stretch of driving is modelled as a random walk in the body
frame whose variance grows linearly with the distance travelled and the rotation performed:

    var(x) = var_x_per_m |ds|        var(y) = var_y_per_m |ds|
    var(yaw) = var_yaw_per_m |ds| + var_yaw_per_rad |dyaw|

(the classic odometry motion model in variance-per-unit form), plus a length-independent part

    C = diag(var_x_const, var_y_const, var_yaw_const)   (m^2, m^2, rad^2, body frame)

present in every pose however short the stretch since the start: an error that does not grow with
the distance (the half-sample lag of sampled wheel speeds, a start-up transient), and a part that
grows with the time spent moving (a white wheel-speed error, as encoder quantisation gives: its
variance grows with time whatever the speed):

    var(x) += var_x_per_s dt        var(yaw) += var_yaw_per_s dt   (only while moving)

"Moving" is one rule, :func:`moving_time`: a step whose predicted twist is not exactly zero. Wheels
that report exactly zero at standstill (the Husky's, most drivers') then add nothing while the
robot is parked, so a parked robot's covariance does not grow; a driver that reports noise at
standstill keeps growing it, as its odometry really drifts. Without the time part, a per-metre
model under-predicts slow driving and turns on the spot: on simulated drives with white encoder
noise the heading error after the first metre was 2-3 times the predicted standard deviation on
some drives (the whole-drive NEES of ``skidkin estimate`` reached 12). A variance per
metre alone can match the error at one horizon only: on the Husky data the rates calibrated at
2 m gave an average NEES of 3.9 at 1 m and 2.0 at 4 m. The constant is added at the pose (rotated
by its heading), never accumulated: it is the same after 1 m as after 100 m.

The calibrator fits the nine values from held-out segment residuals over several horizons; the
node and the prediction API use them to grow the pose covariance and to publish a twist covariance
consistent with the errors actually observed. Files written before the constant or the time part
existed load with them at zero (the old model).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Mapping

import numpy as np

from skidkin_ros.core.kinematics.specs import check_value, INF, ParamSpec

__all__ = ['NOISE_SPECS', 'RATE_NAMES', 'CONST_NAMES', 'TIME_NAMES', 'NoiseModel',
           'moving_time', 'FALLBACK_POSE_DIAGONAL', 'FALLBACK_TWIST_DIAGONAL']

NOISE_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec('var_x_per_m', 'm^2/m', 1e-3, 0.0, INF,
              'longitudinal position variance gained per metre travelled', default_doc='1e-3'),
    ParamSpec('var_y_per_m', 'm^2/m', 1e-3, 0.0, INF,
              'lateral position variance gained per metre travelled', default_doc='1e-3'),
    ParamSpec('var_yaw_per_m', 'rad^2/m', 1e-4, 0.0, INF,
              'heading variance gained per metre travelled', default_doc='1e-4'),
    ParamSpec('var_yaw_per_rad', 'rad^2/rad', 1e-3, 0.0, INF,
              'heading variance gained per radian turned', default_doc='1e-3'),
    ParamSpec('var_x_const', 'm^2', 0.0, 0.0, INF,
              'longitudinal position variance present at any distance (length-independent)',
              default_doc='0'),
    ParamSpec('var_y_const', 'm^2', 0.0, 0.0, INF,
              'lateral position variance present at any distance (length-independent)',
              default_doc='0'),
    ParamSpec('var_yaw_const', 'rad^2', 0.0, 0.0, INF,
              'heading variance present at any distance (length-independent)', default_doc='0'),
    ParamSpec('var_x_per_s', 'm^2/s', 0.0, 0.0, INF,
              'longitudinal position variance gained per second of motion (white wheel-speed '
              'error)', default_doc='0'),
    ParamSpec('var_yaw_per_s', 'rad^2/s', 0.0, 0.0, INF,
              'heading variance gained per second of motion (white wheel-speed error)',
              default_doc='0'),
)
RATE_NAMES = tuple(spec.name for spec in NOISE_SPECS[:4])
CONST_NAMES = tuple(spec.name for spec in NOISE_SPECS[4:7])
TIME_NAMES = tuple(spec.name for spec in NOISE_SPECS[7:])


def moving_time(vx, vy, w, dt_s):
    """Return the time of a step that counts as motion: dt_s unless the twist is exactly zero.

    The one rule (module docstring) for the node, the propagation and the noise fit; it takes
    floats or arrays (element-wise).
    """
    if isinstance(vx, float) and isinstance(vy, float) and isinstance(w, float):
        return dt_s if (vx != 0.0 or vy != 0.0 or w != 0.0) else 0.0
    moving = (np.asarray(vx) != 0.0) | (np.asarray(vy) != 0.0) | (np.asarray(w) != 0.0)
    return np.where(moving, dt_s, 0.0)


# Used when no calibration is loaded: small, never zero (an EKF would trust zeros blindly).
# Order: x, y, z, roll, pitch, yaw (m^2, rad^2) and vx, vy, vz, wx, wy, wz (m^2/s^2, rad^2/s^2).
FALLBACK_POSE_DIAGONAL = (1e-3, 1e-3, 1e6, 1e6, 1e6, 1e-2)
FALLBACK_TWIST_DIAGONAL = (1e-2, 1e-2, 1e6, 1e6, 1e6, 2e-2)


@dataclass(frozen=True)
class NoiseModel:
    """Variance growth rates of one model's odometry error (see module docstring)."""

    var_x_per_m: float
    var_y_per_m: float
    var_yaw_per_m: float
    var_yaw_per_rad: float
    var_x_const: float = 0.0
    var_y_const: float = 0.0
    var_yaw_const: float = 0.0
    var_x_per_s: float = 0.0
    var_yaw_per_s: float = 0.0

    @classmethod
    def from_mapping(cls, values: Mapping[str, float], prefix: str = '') -> 'NoiseModel':
        """Build from named values; a missing constant or time term is zero (older files)."""
        rates = {name: values[name] for name in RATE_NAMES}
        consts = {name: values.get(name, 0.0) for name in CONST_NAMES + TIME_NAMES}
        specs = {spec.name: spec for spec in NOISE_SPECS}
        return cls(**{name: check_value(specs[name], value, prefix)
                      for name, value in {**rates, **consts}.items()})

    @property
    def has_constant(self) -> bool:
        return bool(self.var_x_const or self.var_y_const or self.var_yaw_const)

    def constant_upper(self, yaw_rad: float) -> tuple[float, ...]:
        """World-frame upper triangle (c00, c01, c02, c11, c12, c22) of R(yaw) C R(yaw)^T."""
        cos_t = math.cos(yaw_rad)
        sin_t = math.sin(yaw_rad)
        cx, cy = self.var_x_const, self.var_y_const
        return (cos_t * cos_t * cx + sin_t * sin_t * cy, cos_t * sin_t * (cx - cy), 0.0,
                sin_t * sin_t * cx + cos_t * cos_t * cy, 0.0, self.var_yaw_const)

    def as_dict(self) -> dict[str, float]:
        return {spec.name: float(getattr(self, spec.name)) for spec in NOISE_SPECS}

    def step_covariance(self, distance_m, rotation_rad, moving_s=0.0) -> np.ndarray:
        """Body-frame covariance (..., 3, 3) of (x, y, yaw) gained over one step.

        ``moving_s``: the step's time in motion (:func:`moving_time`).
        """
        ds = np.abs(np.asarray(distance_m, dtype=float))
        dth = np.abs(np.asarray(rotation_rad, dtype=float))
        dt = np.asarray(moving_s, dtype=float)
        cov = np.zeros(np.broadcast(ds, dth, dt).shape + (3, 3))
        cov[..., 0, 0] = self.var_x_per_m * ds + self.var_x_per_s * dt
        cov[..., 1, 1] = self.var_y_per_m * ds
        cov[..., 2, 2] = (self.var_yaw_per_m * ds + self.var_yaw_per_rad * dth
                          + self.var_yaw_per_s * dt)
        return cov

    def step_variances(self, distance_m: float, rotation_rad: float, moving_s: float = 0.0
                       ) -> tuple[float, float, float]:
        """Diagonal of :meth:`step_covariance` for one step, as floats (the node's hot path)."""
        ds = abs(distance_m)
        return (self.var_x_per_m * ds + self.var_x_per_s * moving_s, self.var_y_per_m * ds,
                self.var_yaw_per_m * ds + self.var_yaw_per_rad * abs(rotation_rad)
                + self.var_yaw_per_s * moving_s)

    def twist_variances(self, speed_m_s: float, yaw_rate_rad_s: float,
                        period_s: float, moving: bool = True) -> tuple[float, float, float]:
        """Variances of (v_x, v_y, omega) for one sample of ``period_s``.

        A white velocity error of variance S held for dt adds S dt^2 to the pose; matching it to
        the rate model's rate * |v| dt gives S = rate |v| / dt, and to the time part's
        rate * dt gives S = rate / dt (only while ``moving``).
        """
        v = abs(speed_m_s)
        w = abs(yaw_rate_rad_s)
        time_x, time_yaw = (self.var_x_per_s, self.var_yaw_per_s) if moving else (0.0, 0.0)
        return ((self.var_x_per_m * v + time_x) / period_s,
                self.var_y_per_m * v / period_s,
                (self.var_yaw_per_m * v + self.var_yaw_per_rad * w + time_yaw) / period_s)
