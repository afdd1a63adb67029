"""The five skid-steer kinematic models of Baril et al. (2020), section III.

Each model maps wheel angular velocities y = [omega_l, omega_r] (rad/s) to the body twist
(v_x, v_y, omega) in m/s, m/s, rad/s through a Jacobian J(k) of fixed parameters k:
``twist = J(k) @ y``. All functions are vectorized over arrays of wheel speeds.

Every model defaults to the ideal differential drive of the configured geometry, so a model with
default parameters predicts exactly what ``ideal_dd`` predicts.
"""

from __future__ import annotations

from dataclasses import dataclass
import functools
import math
from typing import Mapping, Sequence

import numpy as np

from skidkin_ros.core.kinematics.specs import check_value, Geometry, INF, ParamSpec
from skidkin_ros.errors import ParameterError

__all__ = [
    'KinematicModel',
    'BoundModel',
    'IdealDD',
    'EddSymmetric',
    'EddAsymmetric',
    'RocModel',
    'FullLinear',
    'MODELS',
    'MODEL_NAMES',
    'get_model',
]

# y0 of the ROC model is kept inside [b * Y0_MIN_FACTOR, b * Y0_MAX_FACTOR]: a fitted (beta_1,
# beta_2) pair may cross the singularity 1 + beta_1 / (1 + beta_2 sqrt(lambda)) = 0, where the
# published yaw rate would otherwise become infinite.
Y0_MIN_FACTOR = 1e-3
Y0_MAX_FACTOR = 1e3
# The largest ICR gain the calibrator fits: y0 <= b/2 (1 + 1000) stays inside the clamp.
ROC_MAX_GAIN = 1000.0


class KinematicModel:
    """Base class: a named model with parameter specs and a vectorized twist function."""

    name: str = ''
    title: str = ''
    reference: str = ''
    formula: str = ''
    params: tuple[ParamSpec, ...] = ()
    predicts_lateral: bool = False

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(spec.name for spec in self.params)

    @property
    def specs(self) -> dict[str, ParamSpec]:
        return {spec.name: spec for spec in self.params}

    def defaults(self, geometry: Geometry) -> dict[str, float]:
        return {spec.name: spec.default_for(geometry) for spec in self.params}

    def vector(self, values: Mapping[str, float], geometry: Geometry) -> np.ndarray:
        """Parameter vector in spec order; missing values take their defaults."""
        unknown = sorted(set(values) - set(self.param_names))
        if unknown:
            raise ParameterError(
                f'model {self.name!r} has no parameter(s) {unknown}; '
                f'its parameters are {list(self.param_names)}')
        merged = {**self.defaults(geometry), **values}
        prefix = f'models.{self.name}.'
        k = np.array([check_value(spec, merged[spec.name], prefix) for spec in self.params])
        self.check_constraints(k)
        return k

    def mapping(self, k: Sequence[float]) -> dict[str, float]:
        return {name: float(value) for name, value in zip(self.param_names, k)}

    def check_constraints(self, k: np.ndarray) -> None:
        """Cross-parameter constraints beyond the per-parameter ranges (none by default)."""

    def rows(self, k: np.ndarray, geometry: Geometry) -> np.ndarray | None:
        """J(k) as one (3, 2) matrix for models linear in the wheel speeds, else None."""
        return None

    def jacobian(self, k: np.ndarray, geometry: Geometry,
                 omega_l: np.ndarray, omega_r: np.ndarray) -> np.ndarray:
        """J(k) with shape (..., 3, 2); depends on the wheel speeds only for the ROC model."""
        rows = self.rows(k, geometry)
        if rows is None:
            raise NotImplementedError
        return np.broadcast_to(rows, np.broadcast(omega_l, omega_r).shape + (3, 2)).copy()

    def scalar_jacobian(self, k: np.ndarray, geometry: Geometry, omega_l: float,
                        omega_r: float) -> tuple[float, ...] | None:
        """J(k) of one wheel-speed pair as 6 floats (row-major) for a speed-dependent model.

        None (the default): the model has no plain-math form, or is linear (see :meth:`rows`).
        """
        return None

    def rows_gradient(self, k: np.ndarray, geometry: Geometry) -> np.ndarray | None:
        """Return dJ(k)/dk as (p, 3, 2) for a model linear in the wheel speeds, else None."""
        return None

    def twist_gradient(self, k: np.ndarray, geometry: Geometry, omega_l: np.ndarray,
                       omega_r: np.ndarray) -> np.ndarray:
        """Return d twist / d k (..., 3, p), exact (the fits' analytic Jacobian)."""
        omega_l = np.asarray(omega_l, dtype=float)
        omega_r = np.asarray(omega_r, dtype=float)
        grad = self.rows_gradient(k, geometry)
        if grad is None:
            raise NotImplementedError
        return (omega_l[..., None, None] * np.moveaxis(grad[..., 0], 0, -1)
                + omega_r[..., None, None] * np.moveaxis(grad[..., 1], 0, -1))

    def twist(self, k: np.ndarray, geometry: Geometry,
              omega_l: np.ndarray, omega_r: np.ndarray) -> np.ndarray:
        """Apply J(k) to the wheel speeds, giving (v_x, v_y, omega) with shape (..., 3)."""
        omega_l = np.asarray(omega_l, dtype=float)
        omega_r = np.asarray(omega_r, dtype=float)
        rows = self.rows(k, geometry)
        if rows is not None:  # linear model: no per-sample Jacobian to build
            # per component, with the arithmetic of omega_l[..., None] * rows[:, 0] +
            # omega_r[..., None] * rows[:, 1] (broadcasting over a last axis of 3 runs
            # numpy's inner loops 3 elements at a time: many times slower on long arrays)
            rows = np.asarray(rows, dtype=float)
            twist = np.empty(np.broadcast_shapes(omega_l.shape, omega_r.shape) + (3,))
            for m in range(3):
                np.multiply(omega_l, rows[m, 0], out=twist[..., m])
                twist[..., m] += omega_r * rows[m, 1]
            return twist
        jac = self.jacobian(k, geometry, omega_l, omega_r)
        return jac[..., 0] * omega_l[..., None] + jac[..., 1] * omega_r[..., None]

    def twist_components(self, k: np.ndarray, geometry: Geometry, omega_l: np.ndarray,
                         omega_r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`twist` as three separate arrays (v_x, v_y, omega), each shaped like omega_l.

        For a linear model each component is computed on its own (contiguous, cheaper to roll
        out); the arithmetic is :meth:`twist`'s, element for element.
        """
        rows = self.rows(k, geometry)
        if rows is None:
            twist = self.twist(k, geometry, omega_l, omega_r)
            return twist[..., 0], twist[..., 1], twist[..., 2]
        omega_l = np.asarray(omega_l, dtype=float)
        omega_r = np.asarray(omega_r, dtype=float)
        (a, b), (c, d), (e, f) = np.asarray(rows, dtype=float)
        return omega_l * a + omega_r * b, omega_l * c + omega_r * d, omega_l * e + omega_r * f

    def bind(self, values: Mapping[str, float], geometry: Geometry) -> 'BoundModel':
        return BoundModel(self, geometry, self.vector(values, geometry))


class IdealDD(KinematicModel):
    """Ideal differential drive: J = r [[1/2, 1/2], [0, 0], [-1/b, 1/b]]. No trained parameter."""

    name = 'ideal_dd'
    title = 'Ideal differential drive'
    reference = 'textbook'
    formula = 'J = r [[1/2, 1/2], [0, 0], [-1/b, 1/b]]'

    def rows(self, k, geometry):
        r, b = geometry.wheel_radius, geometry.track_width
        return np.array([[r / 2, r / 2], [0.0, 0.0], [-r / b, r / b]])

    def rows_gradient(self, k, geometry):
        return np.zeros((0, 3, 2))


class EddSymmetric(KinematicModel):
    """Extended differential drive, symmetric (Mandow 2007).

    J = r alpha [[1/2, 1/2], [0, 0], [-1/b_hat, 1/b_hat]], with b_hat = 2 y0 the virtual
    track width set by the wheels' instantaneous centres of rotation.
    """

    name = 'edd_symmetric'
    title = 'Extended differential drive, symmetric'
    reference = 'Mandow et al. 2007'
    formula = 'J = r alpha [[1/2, 1/2], [0, 0], [-1/b_hat, 1/b_hat]]'
    params = (
        ParamSpec('alpha', '-', 1.0, 0.0, 1.0, 'slip factor of both sides',
                  default_doc='1'),
        ParamSpec('b_hat', 'm', lambda g: g.track_width, 0.0, INF,
                  'virtual track width 2 y0 (ICR distance)', default_doc='b', lower_open=True),
    )

    def rows(self, k, geometry):
        alpha, b_hat = k
        r = geometry.wheel_radius
        return r * alpha * np.array([[0.5, 0.5], [0.0, 0.0], [-1.0 / b_hat, 1.0 / b_hat]])

    def rows_gradient(self, k, geometry):
        alpha, b_hat = k
        r = geometry.wheel_radius
        return np.array([r * np.array([[0.5, 0.5], [0.0, 0.0], [-1.0 / b_hat, 1.0 / b_hat]]),
                         r * alpha * np.array([[0.0, 0.0], [0.0, 0.0],
                                               [1.0 / b_hat ** 2, -1.0 / b_hat ** 2]])])


class EddAsymmetric(KinematicModel):
    """Extended differential drive, asymmetric (Mandow 2007).

    J = r / (y_l - y_r) [[-y_r, y_l], [x_v, -x_v], [-1, 1]] diag(alpha_l, alpha_r), where
    (x_v, y_l) and (x_v, y_r) are the ICRs of the left and right treads in the body frame.
    """

    name = 'edd_asymmetric'
    title = 'Extended differential drive, asymmetric'
    reference = 'Mandow et al. 2007'
    formula = 'J = r/(y_l - y_r) [[-y_r, y_l], [x_v, -x_v], [-1, 1]] diag(alpha_l, alpha_r)'
    predicts_lateral = True
    params = (
        ParamSpec('alpha_l', '-', 1.0, 0.0, 1.0, 'slip factor of the left side',
                  default_doc='1'),
        ParamSpec('alpha_r', '-', 1.0, 0.0, 1.0, 'slip factor of the right side',
                  default_doc='1'),
        ParamSpec('x_v', 'm', 0.0, -INF, INF, 'longitudinal position of the ICRs',
                  default_doc='0'),
        ParamSpec('y_l', 'm', lambda g: g.track_width / 2, 0.0, INF,
                  'lateral position of the left ICR', default_doc='b/2', lower_open=True),
        ParamSpec('y_r', 'm', lambda g: -g.track_width / 2, -INF, 0.0,
                  'lateral position of the right ICR', default_doc='-b/2', upper_open=True),
    )

    def check_constraints(self, k):
        y_l, y_r = k[3], k[4]
        if not y_l > y_r:
            raise ParameterError(
                f'models.{self.name}: y_l ({y_l:g} m) must be greater than y_r ({y_r:g} m); '
                'the left ICR lies on the left (+y) of the right one')

    def rows(self, k, geometry):
        alpha_l, alpha_r, x_v, y_l, y_r = k
        scale = geometry.wheel_radius / (y_l - y_r)
        return scale * np.array([
            [-y_r * alpha_l, y_l * alpha_r],
            [x_v * alpha_l, -x_v * alpha_r],
            [-alpha_l, alpha_r],
        ])

    def rows_gradient(self, k, geometry):
        alpha_l, alpha_r, x_v, y_l, y_r = k
        width = y_l - y_r
        scale = geometry.wheel_radius / width
        rows = self.rows(k, geometry)
        return np.array([
            scale * np.array([[-y_r, 0.0], [x_v, 0.0], [-1.0, 0.0]]),
            scale * np.array([[0.0, y_l], [0.0, -x_v], [0.0, 1.0]]),
            scale * np.array([[0.0, 0.0], [alpha_l, -alpha_r], [0.0, 0.0]]),
            -rows / width + scale * np.array([[0.0, alpha_r], [0.0, 0.0], [0.0, 0.0]]),
            rows / width + scale * np.array([[-alpha_l, 0.0], [0.0, 0.0], [0.0, 0.0]]),
        ])


class RocModel(KinematicModel):
    """Radius-of-curvature based model (Wang et al. 2015).

    The symmetric Jacobian r alpha [[1/2, 1/2], [0, 0], [-1/(2 y0), 1/(2 y0)]] with an ICR
    distance that depends on the path: y0 = b/2 (1 + beta_1 / (1 + beta_2 sqrt(lambda))),
    lambda = |(omega_r + omega_l) / (omega_r - omega_l)|. Evaluated as
    beta_1 sqrt|d| / (sqrt|d| + beta_2 sqrt|s|) so that straight driving (d = 0, lambda = inf)
    and pure rotation (s = 0) stay finite.

    The calibrator keeps beta_1 and beta_2 >= 0, as Wang et al. do (the ICR gain is positive
    and decays as the path straightens): the denominator is then >= sqrt|d| and y0 stays in
    [b/2, b/2 (1 + beta_1)], far from the clamp [b/1000, 1000 b] that guards the singularity
    of a negative beta_2 (a fit that ran into it ended at a clamp, not a minimum). A file may
    still hold any finite value (older files load); beta_2 = 0 is edd_symmetric with
    b_hat = b (1 + beta_1).

    beta_2 >= 0 is part of the model, so a fit that ends on beta_2 = 0 (a robot whose ICR gain
    does not decay along the path, like the Warthog) is a valid constrained minimum: the best
    roc there is, equal to edd_symmetric; it is written, and the model choice, which takes the
    model with fewer parameters when two do as well, then picks edd_symmetric. beta_1 on its
    upper end (1000) is a guard, not part of the model: a fit there stays invalid.
    """

    name = 'roc'
    title = 'Radius-of-curvature based'
    reference = 'Wang et al. 2015'
    formula = ('J = r alpha [[1/2, 1/2], [0, 0], [-1/(2 y0), 1/(2 y0)]], '
               'y0 = b/2 (1 + beta_1/(1 + beta_2 sqrt(lambda)))')
    params = (
        ParamSpec('alpha', '-', 1.0, 0.0, 1.0, 'slip factor of both sides', default_doc='1'),
        ParamSpec('beta_1', '-', 0.0, -INF, INF,
                  'ICR gain at pure rotation (fitted in [0, 1000])', default_doc='0',
                  fit_lower=0.0, fit_upper=ROC_MAX_GAIN),
        ParamSpec('beta_2', '-', 0.0, -INF, INF,
                  'decay of the ICR gain with sqrt(lambda) (fitted >= 0)', default_doc='0',
                  fit_lower=0.0, fit_lower_is_constraint=True),
    )

    @staticmethod
    def icr_distance(k: np.ndarray, geometry: Geometry, omega_l: np.ndarray,
                     omega_r: np.ndarray) -> np.ndarray:
        """y0 (m) for each wheel-speed pair, finite everywhere."""
        _, beta_1, beta_2 = k
        b = geometry.track_width
        root_d = np.sqrt(np.abs(np.asarray(omega_r, float) - omega_l))
        root_s = np.sqrt(np.abs(np.asarray(omega_r, float) + omega_l))
        den = root_d + beta_2 * root_s
        # lambda undefined (standstill) or beta_2 = 0: the gain is beta_1 itself.
        plain = (den == 0.0) & ((beta_2 == 0.0) | (root_s == 0.0))
        safe_den = np.where(den == 0.0, 1.0, den)
        singular = np.copysign(np.inf, beta_1) if beta_1 != 0.0 else 0.0
        gain = np.where(den == 0.0, np.where(plain, beta_1, singular),
                        beta_1 * root_d / safe_den)
        with np.errstate(invalid='ignore'):
            y0 = b / 2 * (1.0 + gain)
        y0 = np.where(np.isnan(y0), b / 2, y0)
        return np.clip(y0, b * Y0_MIN_FACTOR, b * Y0_MAX_FACTOR)

    @staticmethod
    def icr_distance_scalar(k: Sequence[float], geometry: Geometry, omega_l: float,
                            omega_r: float) -> float:
        """Return :meth:`icr_distance` of one wheel-speed pair on plain floats, bit for bit."""
        _, beta_1, beta_2 = (float(v) for v in k)
        b = geometry.track_width
        root_d = math.sqrt(abs(omega_r - omega_l))
        root_s = math.sqrt(abs(omega_r + omega_l))
        den = root_d + beta_2 * root_s
        if den != 0.0:
            gain = beta_1 * root_d / den
        elif beta_2 == 0.0 or root_s == 0.0 or beta_1 == 0.0:
            gain = beta_1
        else:
            gain = math.copysign(math.inf, beta_1)
        y0 = b / 2 * (1.0 + gain)
        if math.isnan(y0):
            y0 = b / 2
        return min(max(y0, b * Y0_MIN_FACTOR), b * Y0_MAX_FACTOR)

    def scalar_jacobian(self, k, geometry, omega_l, omega_r):
        half = geometry.wheel_radius * float(k[0]) / 2
        y0 = self.icr_distance_scalar(k, geometry, omega_l, omega_r)
        scale = geometry.wheel_radius * float(k[0])
        return half, half, 0.0, 0.0, -scale / (2 * y0), scale / (2 * y0)

    def jacobian(self, k, geometry, omega_l, omega_r):
        alpha = k[0]
        r = geometry.wheel_radius
        y0 = self.icr_distance(k, geometry, omega_l, omega_r)
        jac = np.zeros(np.shape(y0) + (3, 2))
        jac[..., 0, :] = r * alpha / 2
        jac[..., 2, 0] = -r * alpha / (2 * y0)
        jac[..., 2, 1] = r * alpha / (2 * y0)
        return jac

    def twist_gradient(self, k, geometry, omega_l, omega_r):
        alpha, beta_1, beta_2 = k
        r, b = geometry.wheel_radius, geometry.track_width
        omega_l = np.asarray(omega_l, dtype=float)
        omega_r = np.asarray(omega_r, dtype=float)
        y0 = self.icr_distance(k, geometry, omega_l, omega_r)
        root_d = np.sqrt(np.abs(omega_r - omega_l))
        root_s = np.sqrt(np.abs(omega_r + omega_l))
        den = root_d + beta_2 * root_s
        plain = (den == 0.0) & ((beta_2 == 0.0) | (root_s == 0.0))
        safe_den = np.where(den == 0.0, 1.0, den)
        # y0 = b/2 (1 + gain): its slope, 0 where clamped or undefined
        moving = (y0 > b * Y0_MIN_FACTOR) & (y0 < b * Y0_MAX_FACTOR)
        d_gain_1 = np.where(den == 0.0, np.where(plain, 1.0, 0.0), root_d / safe_den)
        d_gain_2 = np.where(den == 0.0, 0.0, -beta_1 * root_d * root_s / safe_den ** 2)
        d_w_d_y0 = -r * alpha * (omega_r - omega_l) / (2 * y0 ** 2)
        grad = np.zeros(np.shape(y0) + (3, 3))
        grad[..., 0, 0] = r / 2 * (omega_l + omega_r)
        grad[..., 2, 0] = r * (omega_r - omega_l) / (2 * y0)
        grad[..., 2, 1] = np.where(moving, d_w_d_y0 * b / 2 * d_gain_1, 0.0)
        grad[..., 2, 2] = np.where(moving, d_w_d_y0 * b / 2 * d_gain_2, 0.0)
        return grad


class FullLinear(KinematicModel):
    """Full linear model (Anousaki 2004): J = [[g11, g12], [g21, g22], [g31, g32]]."""

    name = 'full_linear'
    title = 'Full linear'
    reference = 'Anousaki & Kyriakopoulos 2004'
    formula = 'J = [[gamma_11, gamma_12], [gamma_21, gamma_22], [gamma_31, gamma_32]]'
    predicts_lateral = True
    params = (
        ParamSpec('gamma_11', 'm/rad', lambda g: g.wheel_radius / 2, -INF, INF,
                  'v_x per left wheel speed', default_doc='r/2'),
        ParamSpec('gamma_12', 'm/rad', lambda g: g.wheel_radius / 2, -INF, INF,
                  'v_x per right wheel speed', default_doc='r/2'),
        ParamSpec('gamma_21', 'm/rad', 0.0, -INF, INF, 'v_y per left wheel speed',
                  default_doc='0'),
        ParamSpec('gamma_22', 'm/rad', 0.0, -INF, INF, 'v_y per right wheel speed',
                  default_doc='0'),
        ParamSpec('gamma_31', '-', lambda g: -g.wheel_radius / g.track_width, -INF, 0.0,
                  'yaw rate per left wheel speed', default_doc='-r/b'),
        ParamSpec('gamma_32', '-', lambda g: g.wheel_radius / g.track_width, 0.0, INF,
                  'yaw rate per right wheel speed', default_doc='r/b'),
    )

    def rows(self, k, geometry):
        return np.asarray(k, dtype=float).reshape(3, 2)

    def rows_gradient(self, k, geometry):
        return np.eye(6).reshape(6, 3, 2)


@dataclass(frozen=True)
class BoundModel:
    """A model with its geometry and parameter vector fixed: what the integrator runs."""

    model: KinematicModel
    geometry: Geometry
    k: np.ndarray

    @property
    def name(self) -> str:
        return self.model.name

    @property
    def values(self) -> dict[str, float]:
        return self.model.mapping(self.k)

    def twist(self, omega_l, omega_r) -> np.ndarray:
        return self.model.twist(self.k, self.geometry, omega_l, omega_r)

    @functools.cached_property
    def _linear_rows(self) -> tuple[float, ...] | None:
        rows = self.model.rows(self.k, self.geometry)
        return None if rows is None else tuple(np.asarray(rows, dtype=float).ravel().tolist())

    def scalar_twist(self, omega_l: float, omega_r: float) -> tuple[float, float, float]:
        """Twist of one sample as floats: the node's hot path, equal to :meth:`twist` bit for bit.

        For a linear model it performs :meth:`KinematicModel.twist`'s operations in its order
        (left column times omega_l plus right column times omega_r) on plain floats.
        """
        rows = self._linear_rows
        if rows is None:
            rows = self.model.scalar_jacobian(self.k, self.geometry, omega_l, omega_r)
        if rows is None:
            vx, vy, w = np.asarray(self.twist(omega_l, omega_r), dtype=float).tolist()
            return vx, vy, w
        a, b, c, d, e, f = rows
        return omega_l * a + omega_r * b, omega_l * c + omega_r * d, omega_l * e + omega_r * f


MODELS: dict[str, KinematicModel] = {
    model.name: model
    for model in (IdealDD(), EddSymmetric(), EddAsymmetric(), RocModel(), FullLinear())
}
MODEL_NAMES: tuple[str, ...] = tuple(MODELS)


def get_model(name: str) -> KinematicModel:
    """Look a model up by name; an unknown name lists the known ones."""
    try:
        return MODELS[name]
    except KeyError:
        raise ParameterError(
            f'unknown model {name!r}; known models are: {", ".join(MODEL_NAMES)}') from None
