"""The sparse fallback's library of twist terms and the bound on a data-driven correction.

The candidate terms of the base twist and its rate of change (:data:`LIBRARY`, one
:class:`LibraryTerm` each; a new term is one entry), their values (:func:`sparse_features`), and
:func:`bounded_correction`, which keeps any data-driven correction of the twist (the sparse
fallback's, the residual model's) within what the wheels can drive. Used by the extensions of
:mod:`~skidkin_ros.core.kinematics.extensions` and the diagnosis's sparse fit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = [
    'LibraryTerm',
    'LIBRARY',
    'SLIP_LEVER_M',
    'SPARSE_FEATURES',
    'SPARSE_OUTPUTS',
    'bounded_correction',
    'sparse_features',
    'sparse_gradients',
    'LIBRARY_GRADIENTS',
    'speeding_up',
]

# Lever (m) that turns a yaw rate into a speed in the bound of a data-driven correction
# (bounded_correction): the largest the named extensions allow (icr_offset's 2 m).
SLIP_LEVER_M = 2.0


def speeding_up(v: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """Return dv where the speed's magnitude grows (v dv > 0), else 0: the accelerating part."""
    return np.where(v * dv > 0.0, dv, 0.0)


# The sparse fallback: a library of candidate terms of the base twist (v = v_x, w = omega) and
# of its rate of change (dv, dw: backward differences over one wheel sample, as the integrator
# has them). Derivative terms stop at the first derivative: a second difference of wheel speeds
# (jerk) is mostly encoder noise.
@dataclass(frozen=True)
class LibraryTerm:
    """One term of the sparse library: a function of the base twist's v_x, omega and rates.

    ``of(v, w, dv, dw)``; ``signal``: the diagnosis trace signal a residual is plotted against
    for this term.
    """

    name: str
    unit: str
    of: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]
    signal: str


LIBRARY: tuple[LibraryTerm, ...] = (
    LibraryTerm('v', 'm/s', lambda v, w, dv, dw: v, 'body_speed'),
    LibraryTerm('w', 'rad/s', lambda v, w, dv, dw: w, 'yaw_rate'),
    LibraryTerm('v_abs_v', 'm^2/s^2', lambda v, w, dv, dw: v * np.abs(v), 'v_abs_v'),
    LibraryTerm('w_abs_w', 'rad^2/s^2', lambda v, w, dv, dw: w * np.abs(w), 'yaw_rate'),
    LibraryTerm('v_w', 'm rad/s^2', lambda v, w, dv, dw: v * w, 'v_omega'),
    LibraryTerm('abs_v', 'm/s', lambda v, w, dv, dw: np.abs(v), 'body_speed'),
    LibraryTerm('abs_w', 'rad/s', lambda v, w, dv, dw: np.abs(w), 'yaw_rate'),
    LibraryTerm('dv', 'm/s^2', lambda v, w, dv, dw: dv, 'd_body_speed'),
    LibraryTerm('dw', 'rad/s^2', lambda v, w, dv, dw: dw, 'd_yaw_rate'),
    LibraryTerm('dv_up', 'm/s^2', lambda v, w, dv, dw: speeding_up(v, dv), 'speeding_up'),
)
SPARSE_FEATURES: tuple[tuple[str, str], ...] = tuple((term.name, term.unit) for term in LIBRARY)
SPARSE_OUTPUTS: tuple[tuple[str, str], ...] = (('vx', 'm/s'), ('vy', 'm/s'), ('wz', 'rad/s'))


def sparse_features(twist: np.ndarray, rate: np.ndarray | None = None) -> np.ndarray:
    """Return the library terms (..., F) of the base twist and its rate, in LIBRARY order."""
    v = np.asarray(twist)[..., 0]
    w = np.asarray(twist)[..., 2]
    rate = np.zeros(np.shape(twist)) if rate is None else np.asarray(rate, dtype=float)
    dv, dw = rate[..., 0], rate[..., 2]
    return np.stack([term.of(v, w, dv, dw) for term in LIBRARY], axis=-1)


# d term / d (v, w, dv, dw) of each LIBRARY term, by name (Extension.partials of the sparse
# correction; test_extensions checks them against finite differences).
LIBRARY_GRADIENTS: dict[str, Callable[..., tuple]] = {
    'v': lambda v, w, dv, dw: (1.0, 0.0, 0.0, 0.0),
    'w': lambda v, w, dv, dw: (0.0, 1.0, 0.0, 0.0),
    'v_abs_v': lambda v, w, dv, dw: (2.0 * np.abs(v), 0.0, 0.0, 0.0),
    'w_abs_w': lambda v, w, dv, dw: (0.0, 2.0 * np.abs(w), 0.0, 0.0),
    'v_w': lambda v, w, dv, dw: (w, v, 0.0, 0.0),
    'abs_v': lambda v, w, dv, dw: (np.sign(v), 0.0, 0.0, 0.0),
    'abs_w': lambda v, w, dv, dw: (0.0, np.sign(w), 0.0, 0.0),
    'dv': lambda v, w, dv, dw: (0.0, 0.0, 1.0, 0.0),
    'dw': lambda v, w, dv, dw: (0.0, 0.0, 0.0, 1.0),
    'dv_up': lambda v, w, dv, dw: (0.0, 0.0, np.where(v * dv > 0.0, 1.0, 0.0), 0.0),
}


def sparse_gradients(twist: np.ndarray, rate: np.ndarray | None = None) -> np.ndarray:
    """Return d term / d (v, w, dv, dw) of every library term (..., F, 4), in LIBRARY order."""
    v = np.asarray(twist, dtype=float)[..., 0]
    w = np.asarray(twist, dtype=float)[..., 2]
    rate = np.zeros(np.shape(twist)) if rate is None else np.asarray(rate, dtype=float)
    dv, dw = rate[..., 0], rate[..., 2]
    return np.stack([np.stack([np.broadcast_to(np.asarray(g, dtype=float), v.shape)
                               for g in LIBRARY_GRADIENTS[term.name](v, w, dv, dw)], axis=-1)
                     for term in LIBRARY], axis=-2)


def bounded_correction(twist: np.ndarray, correction: np.ndarray) -> np.ndarray:
    """Return twist + correction, each component's change bounded by the motion's own size.

    A slip never moves the body faster than its wheels drive it: v_x and v_y change by at most
    |v_x| + |omega| SLIP_LEVER_M (m/s), omega by at most |omega| + |v_x| / SLIP_LEVER_M (rad/s).
    So a data-driven correction cannot publish an absurd twist, whatever its coefficients or
    inputs (and a robot whose wheels stand still stays still).
    """
    twist = np.asarray(twist, dtype=float)
    v = np.abs(twist[..., 0])
    w = np.abs(twist[..., 2])
    linear = v + w * SLIP_LEVER_M
    angular = w + v / SLIP_LEVER_M
    bound = np.stack([linear, linear, angular], axis=-1)
    return twist + np.clip(correction, -bound, bound)
