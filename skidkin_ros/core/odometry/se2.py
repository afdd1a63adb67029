"""The exact SE(2) step and the batch rollouts built on it.

Over an interval of constant body twist the pose advances by the exact SE(2) exponential, with a
series branch for small rotations that is continuous with the closed form. :func:`step_scalar`
(the streaming integrator's step, :mod:`~skidkin_ros.core.odometry.integrator`) and the batch
rollouts (:func:`body_increment`, :func:`compose`, :func:`rollout_segments`, used for fitting)
perform the same operations in the same order, so they agree to the last bit; they share this
module so that invariant has one home. The fits' rollouts may ask for ``exact=False``: the same
step with the sines and cosines taken from one tangent of the half angle (:func:`sin_cos`),
equal to a few 1e-16 and several times cheaper; what the node and ``skidkin predict`` run never
does.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    'SMALL_ANGLE_RAD',
    'body_increment',
    'compose',
    'step_scalar',
    'rollout',
    'rollout_segments',
    'rollout_columns',
    'sin_cos',
    'wrap_angle',
]

# Below this rotation per step the closed form loses digits; the series is exact to ~1e-22 there.
SMALL_ANGLE_RAD = 1e-3


def sin_cos(angle, exact: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Return (sin, cos) of an array of angles.

    ``exact``: numpy's sin and cos (what :func:`step_scalar` uses, bit for bit). Otherwise from
    t = tan(a / 2): sin a = 2 t / (1 + t^2), cos a = (1 - t^2) / (1 + t^2), within a few 1e-16
    of them. numpy runs float64 sin and cos element by element but tan in SIMD: the half-angle
    form costs about a fifth of the pair, and the fits' rollouts take it.
    """
    if exact:
        return np.sin(angle), np.cos(angle)
    t = np.tan(0.5 * np.asarray(angle, dtype=float))
    t2 = t * t
    inverse = 1.0 / (1.0 + t2)
    return 2.0 * t * inverse, (1.0 - t2) * inverse


def _sinc_terms(dtheta: np.ndarray, exact: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Return sin(a)/a and (1 - cos a)/a, continuous through a = 0.

    The closed form everywhere, then the series where |a| is small (rare at usual sampling
    rates, so the series is evaluated on those elements only). ``exact=False``: the closed form
    from t = tan(a / 2) (:func:`sin_cos`), 2 t / (a (1 + t^2)) and t times that (no
    cancellation in 1 - cos a).
    """
    given = np.asarray(dtheta, dtype=float)
    a = np.atleast_1d(given)
    small = np.abs(a) < SMALL_ANGLE_RAD
    any_small = bool(small.any())
    safe = np.where(small, 1.0, a) if any_small else a
    if exact:
        sin_a = np.sin(safe) / safe
        cos_a = (1.0 - np.cos(safe)) / safe
    else:
        t = np.tan(0.5 * safe)
        sin_a = 2.0 * t / (safe * (1.0 + t * t))
        cos_a = t * sin_a
    if any_small:
        s = a[small]
        s2 = s * s
        sin_a[small] = 1.0 - s2 / 6.0 + s2 * s2 / 120.0
        cos_a[small] = s / 2.0 - s * s2 / 24.0 + s * s2 * s2 / 720.0
    return sin_a.reshape(given.shape), cos_a.reshape(given.shape)


def _sinc_scalar(a: float) -> tuple[float, float]:
    """Scalar form of :func:`_sinc_terms`: the same operations in the same order."""
    if abs(a) < SMALL_ANGLE_RAD:
        a2 = a * a
        return (1.0 - a2 / 6.0 + a2 * a2 / 120.0,
                a / 2.0 - a * a2 / 24.0 + a * a2 * a2 / 720.0)
    # numpy's sin/cos (not math's): the batch rollout uses them, and libm may differ by an ulp.
    return float(np.sin(a)) / a, (1.0 - float(np.cos(a))) / a


def step_scalar(x: float, y: float, theta: float, v_x: float, v_y: float, omega: float,
                dt_s: float) -> tuple[float, float, float, float, float]:
    """One integrator step on plain floats: returns (x', y', theta', dx, dy).

    The same operations in the same order as :func:`body_increment` and :func:`compose` (and as
    :func:`rollout_segments`' cumulative sums), so a stream of these steps reproduces the batch
    rollout bit for bit, at a fraction of the cost of numpy on scalars (the node's hot path).
    """
    dtheta = omega * dt_s
    sin_a, cos_a = _sinc_scalar(dtheta)
    s = sin_a * dt_s
    c = cos_a * dt_s
    dx = v_x * s - v_y * c
    dy = v_x * c + v_y * s
    cos_t = float(np.cos(theta))
    sin_t = float(np.sin(theta))
    return (x + (cos_t * dx - sin_t * dy), y + (sin_t * dx + cos_t * dy), theta + dtheta,
            dx, dy)


def body_increment(v_x, v_y, omega, dt_s, exact: bool = True):
    """Pose change (dx, dy, dtheta) in the start frame for a constant twist held for dt_s.

    ``exact=False``: the fits' cheaper trigonometry (:func:`sin_cos`).
    """
    dtheta = np.asarray(omega, dtype=float) * dt_s
    sin_a, cos_a = _sinc_terms(dtheta, exact)
    s = sin_a * dt_s
    c = cos_a * dt_s
    dx = v_x * s - v_y * c
    dy = v_x * c + v_y * s
    return dx, dy, dtheta


def compose(x, y, theta, dx, dy, dtheta, exact: bool = True):
    """Apply a body-frame increment to a world pose (vectorized; ``exact``: :func:`sin_cos`)."""
    sin_t, cos_t = sin_cos(theta, exact)
    return (x + (cos_t * dx - sin_t * dy),
            y + (sin_t * dx + cos_t * dy),
            theta + dtheta)


def wrap_angle(angle):
    """Wrap to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def rollout_segments(twist: np.ndarray, dt_s: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Integrate many segments at once.

    twist: (N, L, 3) body twists held over each step; dt_s: (N, L) step durations (0 for
    padding); start: (N, 3) start poses (x, y, yaw). Returns poses (N, L + 1, 3): the start and
    the pose after each step. The heading of every step is known before any position, so the
    whole rollout is three cumulative sums; no Python loop over time.
    """
    twist = np.asarray(twist, dtype=float)
    x, y, theta = rollout_columns(twist[..., 0], twist[..., 1], twist[..., 2], dt_s, start)
    return np.stack([x, y, theta], axis=-1)


def rollout_columns(v_x: np.ndarray, v_y: np.ndarray, omega: np.ndarray, dt_s: np.ndarray,
                    start: np.ndarray, exact: bool = True
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`rollout_segments` on the twist components, each (N, L); returns x, y, yaw (N, L+1).

    The fitting calls this with contiguous components (cheaper than strided views of an
    (N, L, 3) array); the arithmetic is the same, element for element (``exact=False``: the
    cheaper trigonometry of :func:`sin_cos`, to rounding).
    """
    dt_s = np.asarray(dt_s, dtype=float)
    start = np.asarray(start, dtype=float)
    dx, dy, dtheta = body_increment(v_x, v_y, omega, dt_s, exact)
    theta = np.cumsum(np.concatenate([start[:, 2:3], dtheta], axis=1), axis=1)
    sin_t, cos_t = sin_cos(theta[:, :-1], exact)
    step_x = cos_t * dx - sin_t * dy
    step_y = sin_t * dx + cos_t * dy
    x = np.cumsum(np.concatenate([start[:, 0:1], step_x], axis=1), axis=1)
    y = np.cumsum(np.concatenate([start[:, 1:2], step_y], axis=1), axis=1)
    return x, y, theta


def rollout(twist: np.ndarray, dt_s: np.ndarray, start=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Integrate one sequence: twist (L, 3), dt_s (L,) -> poses (L + 1, 3)."""
    return rollout_segments(np.asarray(twist)[None], np.asarray(dt_s)[None],
                            np.asarray(start, dtype=float)[None])[0]
