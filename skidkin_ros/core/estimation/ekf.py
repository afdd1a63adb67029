"""A small reference EKF on the planar pose (x, y, yaw): skidkin's prediction, absolute fixes.

The prediction step IS skidkin's: wheel speeds are held from each sample's stamp to the next
(the ``starting`` sample-interval convention; feed it
:func:`~skidkin_ros.core.odometry.interval.held_wheels` of the samples for another one, which looks
one sample ahead and is for offline use) and every interval is one
:func:`skidkin_ros.core.odometry.propagation.propagate_step` (the exact SE(2) step of the
integrator and its first-order covariance with the calibrated NoiseModel). The correction is a
standard EKF update with an absolute pose measurement (a GNSS or lidar fix: position, optionally
yaw) of known covariance; the yaw innovation is wrapped.

Example (wheel samples at 20 Hz, a fix every second)::

    from skidkin_ros.core.estimation.ekf import PlanarEkf, PoseFix

    # calibrated under interval ending or midpoint: samples = held_wheels(samples, interval)
    ekf = PlanarEkf(bound_model, noise, pose=start_pose, cov=np.diag([0.01, 0.01, 0.001]))
    for t_ns, omega_l, omega_r in samples:
        ekf.predict(t_ns, omega_l, omega_r)
        if t_ns in fixes:
            ekf.correct(fixes[t_ns])   # PoseFix(t_ns, x, y, yaw_rad or None, cov)
    print(ekf.pose, ekf.cov)
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Sequence

import numpy as np

from skidkin_ros.core.odometry.integrator import is_stateful, TwistSource, wrap_angle
from skidkin_ros.core.odometry.noise import NoiseModel
from skidkin_ros.core.odometry.propagation import increment_input_jacobian, propagate_step
from skidkin_ros.errors import DataError, ParameterError

__all__ = ['PoseFix', 'Innovation', 'PlanarEkf']


@dataclass(frozen=True)
class PoseFix:
    """An absolute pose measurement at ``t_ns``: x, y (m) and, when known, yaw (rad).

    ``cov`` is 2 x 2 (m^2) for a position fix or 3 x 3 (m^2, rad^2) with yaw.
    """

    t_ns: int
    x: float
    y: float
    yaw_rad: float | None
    cov: np.ndarray

    def __post_init__(self) -> None:
        dim = 2 if self.yaw_rad is None else 3
        cov = np.asarray(self.cov, dtype=float)
        if cov.shape != (dim, dim):
            raise ParameterError(f'PoseFix.cov must be {dim} x {dim} for a fix '
                                 f'{"without" if dim == 2 else "with"} yaw, got {cov.shape}')
        if not np.all(np.isfinite(cov)) or np.any(np.linalg.eigvalsh(cov) <= 0.0):
            raise ParameterError('PoseFix.cov must be finite and positive definite (m^2, rad^2)')
        object.__setattr__(self, 'cov', cov)

    @property
    def vector(self) -> np.ndarray:
        values = [self.x, self.y] + ([] if self.yaw_rad is None else [self.yaw_rad])
        return np.asarray(values, dtype=float)


@dataclass(frozen=True)
class Innovation:
    """What one correction saw: innovation, its covariance and the NIS (chi2 with dim dof)."""

    t_ns: int
    residual: np.ndarray
    cov: np.ndarray
    nis: float


class PlanarEkf:
    """EKF on (x, y, yaw): :meth:`predict` per wheel sample, :meth:`correct` per fix.

    ``source`` is a bound kinematic model (``model.bind(values, geometry)``), ``noise`` its
    calibrated NoiseModel (None: no process noise, only ``input_variance``, the wheel-speed
    variance in rad^2/s^2, propagated through the model). The state holds at ``t_ns``; yaw is
    kept unwrapped (continuous) like the integrator's.
    """

    def __init__(self, source: TwistSource, noise: NoiseModel | None,
                 pose: Sequence[float] = (0.0, 0.0, 0.0), cov: np.ndarray | None = None,
                 input_variance: float = 0.0) -> None:
        if is_stateful(source):
            raise ParameterError(
                'PlanarEkf takes a plain kinematic model (model.bind(values, geometry)); an '
                'augmented model carries state between wheel samples, which this filter does not '
                'split at fix times yet. Use its base model here, or propagation.predict() for '
                "the augmented model's prediction")
        self.source = source
        self.noise = noise
        self.input_variance = float(input_variance)
        self.pose = np.asarray(pose, dtype=float).copy()
        self.cov = np.zeros((3, 3)) if cov is None else np.asarray(cov, dtype=float).copy()
        if self.pose.shape != (3,) or self.cov.shape != (3, 3):
            raise ParameterError('PlanarEkf: pose must be (x, y, yaw) and cov 3 x 3')
        self.t_ns: int | None = None
        self.held_speeds = (0.0, 0.0)

    def _advance(self, t_ns: int) -> None:
        """Integrate the held speeds from the state time to ``t_ns``."""
        if self.t_ns is None:
            self.t_ns = int(t_ns)
            return
        dt_s = (int(t_ns) - self.t_ns) * 1e-9
        if dt_s < 0.0:
            raise DataError(f'PlanarEkf: stamp {t_ns} ns is older than the state '
                            f'({self.t_ns} ns); feed samples and fixes in time order')
        if dt_s > 0.0:
            omega_l, omega_r = self.held_speeds
            twist = np.asarray(self.source.twist(omega_l, omega_r), dtype=float)
            jac_in = (increment_input_jacobian(self.source, omega_l, omega_r, dt_s)
                      if self.input_variance > 0.0 else None)
            self.pose, self.cov = propagate_step(self.pose, self.cov, twist, dt_s, self.noise,
                                                 jac_in, self.input_variance)
        self.t_ns = int(t_ns)

    def predict(self, t_ns: int, omega_l: float, omega_r: float) -> None:
        """Advance to the wheel sample at ``t_ns`` with the held speeds, then hold the new ones."""
        if not (math.isfinite(omega_l) and math.isfinite(omega_r)):
            raise DataError(f'PlanarEkf: non-finite wheel speed ({omega_l}, {omega_r}) rad/s')
        self._advance(t_ns)
        self.held_speeds = (float(omega_l), float(omega_r))

    def correct(self, fix: PoseFix) -> Innovation:
        """Predict up to the fix time (held speeds), then apply the EKF update (Joseph form)."""
        self._advance(fix.t_ns)
        dim = fix.vector.size
        jac = np.eye(3)[:dim]
        residual = fix.vector - self.pose[:dim]
        if dim == 3:
            residual[2] = float(wrap_angle(residual[2]))
        s_cov = jac @ self.cov @ jac.T + fix.cov
        gain = np.linalg.solve(s_cov, jac @ self.cov).T
        self.pose = self.pose + gain @ residual
        joseph = np.eye(3) - gain @ jac
        cov = joseph @ self.cov @ joseph.T + gain @ fix.cov @ gain.T
        self.cov = 0.5 * (cov + cov.T)
        nis = float(residual @ np.linalg.solve(s_cov, residual))
        return Innovation(int(fix.t_ns), residual, s_cov, nis)
