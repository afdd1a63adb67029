"""The data-driven residual model: a correction of the body twist learned from the data.

What the named extensions cannot express, a smooth function of the wheel-speed state can: the
body twist gains a correction c(z) = C phi(z), linear in its coefficients C and built from a fixed,
systematic library phi of the state z = (v, w, dv, dw) (the base model's forward speed and yaw
rate and their rates of change, as the integrator has them). The library grows in levels, each a
richer family of smooth functions:

1. the signals and their magnitudes: v, w, |v|, |w|;
2. every product of a signal and a signal's magnitude (v|v|, w|w|, v|w|, w|v|), v w, |v||w|,
   and smooth signs of v and w (x / (|x| + 0.1), a direction-dependent offset);
3. the rates: dv, dw, their speeding-up parts (the rate while the magnitude grows), and the
   speed times the forward rate and its magnitude, v dv and v |dv| (a slip proportional to the
   acceleration, or to its size: load transfer);
4. the turn fraction s = w / (|v| + |w| + TURN_WIDTH) of the scaled inputs (how much of the motion
   is turning: a bounded function of the curvature, the wheel speed ratio's role) times the
   signals: v s^2, w s^2, v |s|, w |s| (a slip that depends on how tight the turn is, whatever
   the speed);
5. the cubic terms v^3, w^3, v^2 w, v w^2;
6. spline terms: each signal times a hinge max(|x| - knot, 0) of its own or the other signal's
   magnitude, knots at a third and two thirds of the range (a piecewise-linear slope: a slip
   that starts, or saturates, at some speed or turn rate, which polynomials fit poorly);
7. bumps over the plane (v, w): each signal times a tent product
   max(1 - |v - c_v| / h, 0) max(1 - |w - c_w| / h, 0), centres on a 3 x 3 grid at -h, 0, h
   (h = BUMP_WIDTH, half the scaled range): a piecewise-bilinear surface, the two-dimensional
   hinge (a slip confined to one region of speeds and turn rates, such as a bump of a random
   smooth function, which no product of one-signal terms follows).

Every input is first clamped to the range the model was fitted on (``<input>_lo``,
``<input>_hi``, stored with the coefficients) and scaled by that range's largest magnitude, so
each term lies in [-1, 1] and a polynomial cannot run away outside the data: beyond the range the
correction holds the value it has at the edge. The change of each twist component is then
bounded by the motion's own size
(:func:`~skidkin_ros.core.kinematics.extensions.bounded_correction`).
Every term vanishes at rest except the rate terms, so a robot standing still stays still.

The coefficients are fitted by Bayesian linear regression on the per-pose body-twist residuals
(:mod:`skidkin_ros.core.calibration.diagnosis.regression`), the level on held-out likelihood.

The batch form (arrays) and the node's per-sample form (floats) run the same operations in the
same order, term by term (no matrix product, no transcendental function), so they agree bit for
bit. This module stays over 500 lines for that reason: the library's terms, their gradients and
the batch, per-sample and planned forms of the correction must change together; split across
modules, a term edited in one would drift from its float form in another.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

__all__ = ['INPUTS', 'TERMS', 'LEVELS', 'TERM_INPUTS', 'INPUT_SIGNALS', 'OUTPUTS', 'SIGN_WIDTH',
           'TURN_WIDTH', 'KNOTS', 'BUMP_WIDTH', 'BUMP_CENTRES',
           'term_names', 'features',
           'scalar_features', 'correction', 'scalar_correction', 'correction_plan',
           'scalar_planned_correction', 'scalar_terms', 'coefficient_names',
           'range_names', 'input_values', 'LEGACY_TERMS', 'LEGACY_LAYOUTS', 'upgrade_covariance',
           'TERM_GRADIENTS', 'feature_gradients', 'correction_gradient', 'used_terms']

# The state the correction is a function of: (name, unit, what it is).
INPUTS: tuple[tuple[str, str, str], ...] = (
    ('v', 'm/s', 'base forward speed'),
    ('w', 'rad/s', 'base yaw rate'),
    ('dv', 'm/s^2', 'rate of the base forward speed'),
    ('dw', 'rad/s^2', 'rate of the base yaw rate'),
)
OUTPUTS: tuple[tuple[str, str], ...] = (('vx', 'm/s'), ('vy', 'm/s'), ('wz', 'rad/s'))
# Width of the smooth sign x / (|x| + SIGN_WIDTH), in scaled units (a tenth of the range).
SIGN_WIDTH = 0.1
# Knots of the spline terms on the magnitudes (scaled units: thirds of the range).
KNOTS = (1.0 / 6.0, 1.0 / 3.0, 0.5, 2.0 / 3.0, 5.0 / 6.0)
# Added to |v| + |w| (scaled units) in the turn fraction, so that it is defined at rest.
TURN_WIDTH = 0.05
# Half-width of the tents of the bump terms and their centres on each scaled input.
BUMP_WIDTH = 0.5
BUMP_CENTRES = (-0.5, 0.0, 0.5)


def _sign(x):
    return x / (abs(x) + SIGN_WIDTH)


def _turn(p, q):
    """Return the turn fraction q / (|p| + |q| + TURN_WIDTH), in [-1, 1]."""
    return q / (abs(p) + abs(q) + TURN_WIDTH)


def _hinge(x, knot: float):
    """Return max(|x| - knot, 0) (on floats or arrays alike): a spline knot on a magnitude."""
    if isinstance(x, np.ndarray):
        return np.maximum(np.abs(x) - knot, 0.0)
    return max(abs(x) - knot, 0.0)


def _up(x, dx):
    """Return dx where |x| grows (x dx > 0), else 0 (on floats or arrays alike)."""
    if isinstance(x, np.ndarray) or isinstance(dx, np.ndarray):
        return np.where(x * dx > 0.0, dx, 0.0)
    return dx if x * dx > 0.0 else 0.0


def _tent(x, centre: float):
    """Return max(1 - |x - centre| / BUMP_WIDTH, 0) (on floats or arrays alike)."""
    if isinstance(x, np.ndarray):
        return np.maximum(1.0 - np.abs(x - centre) / BUMP_WIDTH, 0.0)
    return max(1.0 - abs(x - centre) / BUMP_WIDTH, 0.0)


def _tent_slope(x, centre: float):
    """Return d _tent / dx: -sign(x - centre) / BUMP_WIDTH inside the tent, 0 outside."""
    return np.where(np.abs(x - centre) < BUMP_WIDTH, -np.sign(x - centre) / BUMP_WIDTH, 0.0)


def _bump_term(x: str, cv: float, cw: float) -> Callable[..., object]:
    """Return the term x * tent(v, cv) * tent(w, cw) of the scaled inputs, x = v or w."""
    if x == 'v':
        return lambda p, q, a, b: p * (_tent(p, cv) * _tent(q, cw))
    return lambda p, q, a, b: q * (_tent(p, cv) * _tent(q, cw))


def _bump_term_gradient(x: str, cv: float, cw: float) -> Callable[..., object]:
    """Return the gradient of :func:`_bump_term` by (p, q, a, b)."""
    def gradient(p, q, a, b):
        tp, tq = _tent(p, cv), _tent(q, cw)
        sp, sq = _tent_slope(p, cv), _tent_slope(q, cw)
        own = p if x == 'v' else q
        return (own * sp * tq + (tp * tq if x == 'v' else 0.0),
                own * tp * sq + (tp * tq if x == 'w' else 0.0), 0.0, 0.0)
    return gradient


def _bump_name(x: str, i: int, j: int) -> str:
    return f'{x}_bump{i + 1}{j + 1}'


def _hinge_term(x: str, knot: float) -> Callable[..., object]:
    """Return the term x * max(|x| - knot, 0) of the scaled forward speed or yaw rate."""
    if x == 'v':
        return lambda p, q, a, b: p * _hinge(p, knot)
    return lambda p, q, a, b: q * _hinge(q, knot)


def _hinge_slope(x, knot: float):
    """Return d max(|x| - knot, 0) / dx: sign(x) beyond the knot, 0 inside (floats or arrays)."""
    return np.where(np.abs(x) > knot, np.sign(x), 0.0)


def _turn_product_gradient(p, q, x: str, power: int):
    """Return d (x s^2) or d (x |s|) / d (p, q, a, b), s the turn fraction, x = p or q."""
    d = np.abs(p) + np.abs(q) + TURN_WIDTH
    s = q / d
    ds_dp = -q * np.sign(p) / (d * d)
    ds_dq = (np.abs(p) + TURN_WIDTH) / (d * d)
    if power == 2:
        f, df = s * s, 2.0 * s
    else:
        f, df = np.abs(s), np.sign(s)
    x_value = p if x == 'v' else q
    grad_p = x_value * df * ds_dp + (f if x == 'v' else 0.0)
    grad_q = x_value * df * ds_dq + (f if x == 'w' else 0.0)
    return (grad_p, grad_q, 0.0, 0.0)


def _cross_hinge_gradient(p, q, x: str, knot: float):
    """Return the gradient of p * max(|q| - knot, 0) (x = 'v') or q * max(|p| - knot, 0)."""
    if x == 'v':
        return (_hinge(q, knot), p * _hinge_slope(q, knot), 0.0, 0.0)
    return (q * _hinge_slope(p, knot), _hinge(p, knot), 0.0, 0.0)


def _hinge_term_gradient(x: str, knot: float) -> Callable[..., object]:
    """Return the gradient of x * max(|x| - knot, 0) (see _hinge_term)."""
    if x == 'v':
        return lambda p, q, a, b: (_hinge(p, knot) + p * _hinge_slope(p, knot), 0.0, 0.0, 0.0)
    return lambda p, q, a, b: (0.0, _hinge(q, knot) + q * _hinge_slope(q, knot), 0.0, 0.0)


# (name, level, function of the scaled inputs (p, q, a, b) = (v, w, dv, dw), signal it follows)
TermFn = Callable[..., object]
TERMS: tuple[tuple[str, int, TermFn, str], ...] = (
    ('v', 1, lambda p, q, a, b: p, 'body_speed'),
    ('w', 1, lambda p, q, a, b: q, 'yaw_rate'),
    ('abs_v', 1, lambda p, q, a, b: abs(p), 'body_speed'),
    ('abs_w', 1, lambda p, q, a, b: abs(q), 'yaw_rate'),
    ('v_abs_v', 2, lambda p, q, a, b: p * abs(p), 'body_speed'),
    ('w_abs_w', 2, lambda p, q, a, b: q * abs(q), 'yaw_rate'),
    ('v_w', 2, lambda p, q, a, b: p * q, 'v_omega'),
    ('v_abs_w', 2, lambda p, q, a, b: p * abs(q), 'body_speed'),
    ('w_abs_v', 2, lambda p, q, a, b: q * abs(p), 'yaw_rate'),
    ('abs_v_abs_w', 2, lambda p, q, a, b: abs(p) * abs(q), 'v_omega'),
    ('sign_v', 2, lambda p, q, a, b: _sign(p), 'direction'),
    ('sign_w', 2, lambda p, q, a, b: _sign(q), 'yaw_rate'),
    ('dv', 3, lambda p, q, a, b: a, 'd_body_speed'),
    ('dw', 3, lambda p, q, a, b: b, 'd_yaw_rate'),
    ('dv_up', 3, lambda p, q, a, b: _up(p, a), 'speeding_up'),
    ('dw_up', 3, lambda p, q, a, b: _up(q, b), 'd_yaw_rate'),
    ('v_dv', 3, lambda p, q, a, b: p * a, 'd_body_speed'),
    ('v_abs_dv', 3, lambda p, q, a, b: p * abs(a), 'd_body_speed'),
    ('v_s2', 4, lambda p, q, a, b: p * _turn(p, q) * _turn(p, q), 'curvature'),
    ('w_s2', 4, lambda p, q, a, b: q * _turn(p, q) * _turn(p, q), 'curvature'),
    ('v_abs_s', 4, lambda p, q, a, b: p * abs(_turn(p, q)), 'curvature'),
    ('w_abs_s', 4, lambda p, q, a, b: q * abs(_turn(p, q)), 'curvature'),
    ('v3', 5, lambda p, q, a, b: p * p * p, 'body_speed'),
    ('w3', 5, lambda p, q, a, b: q * q * q, 'yaw_rate'),
    ('v2_w', 5, lambda p, q, a, b: p * p * q, 'v_omega'),
    ('v_w2', 5, lambda p, q, a, b: p * q * q, 'v_omega'),
    ('v_w_hinge1', 6, lambda p, q, a, b: p * _hinge(q, KNOTS[1]), 'v_omega'),
    ('v_w_hinge2', 6, lambda p, q, a, b: p * _hinge(q, KNOTS[3]), 'v_omega'),
    ('w_v_hinge1', 6, lambda p, q, a, b: q * _hinge(p, KNOTS[1]), 'v_omega'),
    ('w_v_hinge2', 6, lambda p, q, a, b: q * _hinge(p, KNOTS[3]), 'v_omega'),
) + tuple((f'{x}_hinge{i + 1}', 6, _hinge_term(x, knot), signal)
          for x, signal in (('v', 'body_speed'), ('w', 'yaw_rate'))
          for i, knot in enumerate(KNOTS)) + tuple(
    (_bump_name(x, i, j), 7, _bump_term(x, cv, cw), signal)
    for x, signal in (('v', 'body_speed'), ('w', 'yaw_rate'))
    for i, cv in enumerate(BUMP_CENTRES) for j, cw in enumerate(BUMP_CENTRES))
# d term / d (p, q, a, b) of each term, by name, next to the terms: a change of a term is a
# change of its row here too (Extension.partials of the residual model; test_extensions checks
# every term against finite differences).
TERM_GRADIENTS: dict[str, TermFn] = {
    'v': lambda p, q, a, b: (1.0, 0.0, 0.0, 0.0),
    'w': lambda p, q, a, b: (0.0, 1.0, 0.0, 0.0),
    'abs_v': lambda p, q, a, b: (np.sign(p), 0.0, 0.0, 0.0),
    'abs_w': lambda p, q, a, b: (0.0, np.sign(q), 0.0, 0.0),
    'v_abs_v': lambda p, q, a, b: (2.0 * abs(p), 0.0, 0.0, 0.0),
    'w_abs_w': lambda p, q, a, b: (0.0, 2.0 * abs(q), 0.0, 0.0),
    'v_w': lambda p, q, a, b: (q, p, 0.0, 0.0),
    'v_abs_w': lambda p, q, a, b: (abs(q), p * np.sign(q), 0.0, 0.0),
    'w_abs_v': lambda p, q, a, b: (q * np.sign(p), abs(p), 0.0, 0.0),
    'abs_v_abs_w': lambda p, q, a, b: (np.sign(p) * abs(q), abs(p) * np.sign(q), 0.0, 0.0),
    'sign_v': lambda p, q, a, b: (SIGN_WIDTH / (abs(p) + SIGN_WIDTH) ** 2, 0.0, 0.0, 0.0),
    'sign_w': lambda p, q, a, b: (0.0, SIGN_WIDTH / (abs(q) + SIGN_WIDTH) ** 2, 0.0, 0.0),
    'dv': lambda p, q, a, b: (0.0, 0.0, 1.0, 0.0),
    'dw': lambda p, q, a, b: (0.0, 0.0, 0.0, 1.0),
    'dv_up': lambda p, q, a, b: (0.0, 0.0, np.where(p * a > 0.0, 1.0, 0.0), 0.0),
    'dw_up': lambda p, q, a, b: (0.0, 0.0, 0.0, np.where(q * b > 0.0, 1.0, 0.0)),
    'v_dv': lambda p, q, a, b: (a, 0.0, p, 0.0),
    'v_abs_dv': lambda p, q, a, b: (abs(a), 0.0, p * np.sign(a), 0.0),
    'v_s2': lambda p, q, a, b: _turn_product_gradient(p, q, 'v', 2),
    'w_s2': lambda p, q, a, b: _turn_product_gradient(p, q, 'w', 2),
    'v_abs_s': lambda p, q, a, b: _turn_product_gradient(p, q, 'v', 1),
    'w_abs_s': lambda p, q, a, b: _turn_product_gradient(p, q, 'w', 1),
    'v_w_hinge1': lambda p, q, a, b: _cross_hinge_gradient(p, q, 'v', KNOTS[1]),
    'v_w_hinge2': lambda p, q, a, b: _cross_hinge_gradient(p, q, 'v', KNOTS[3]),
    'w_v_hinge1': lambda p, q, a, b: _cross_hinge_gradient(p, q, 'w', KNOTS[1]),
    'w_v_hinge2': lambda p, q, a, b: _cross_hinge_gradient(p, q, 'w', KNOTS[3]),
    'v3': lambda p, q, a, b: (3.0 * p * p, 0.0, 0.0, 0.0),
    'w3': lambda p, q, a, b: (0.0, 3.0 * q * q, 0.0, 0.0),
    'v2_w': lambda p, q, a, b: (2.0 * p * q, p * p, 0.0, 0.0),
    'v_w2': lambda p, q, a, b: (q * q, 2.0 * p * q, 0.0, 0.0),
}
TERM_GRADIENTS.update({f'{x}_hinge{i + 1}': _hinge_term_gradient(x, knot)
                       for x in ('v', 'w') for i, knot in enumerate(KNOTS)})
TERM_GRADIENTS.update({_bump_name(x, i, j): _bump_term_gradient(x, cv, cw)
                       for x in ('v', 'w') for i, cv in enumerate(BUMP_CENTRES)
                       for j, cw in enumerate(BUMP_CENTRES)})
LEVELS: tuple[int, ...] = tuple(sorted({level for _, level, _, _ in TERMS}))
# Which inputs each term is a function of (for the interpretation: what the correction follows).
TERM_INPUTS: dict[str, str] = {
    'v': 'v', 'w': 'w', 'abs_v': 'v', 'abs_w': 'w', 'v_abs_v': 'v', 'w_abs_w': 'w',
    'v_w': 'v*w', 'v_abs_w': 'v*w', 'w_abs_v': 'v*w', 'abs_v_abs_w': 'v*w', 'sign_v': 'v',
    'sign_w': 'w', 'dv': 'dv', 'dw': 'dw', 'dv_up': 'dv', 'dw_up': 'dw', 'v_dv': 'dv',
    'v_abs_dv': 'dv', 'v_s2': 'turn', 'w_s2': 'turn', 'v_abs_s': 'turn', 'w_abs_s': 'turn',
    'v3': 'v', 'w3': 'w', 'v2_w': 'v*w', 'v_w2': 'v*w', 'v_w_hinge1': 'v*w', 'v_w_hinge2': 'v*w',
    'w_v_hinge1': 'v*w', 'w_v_hinge2': 'v*w',
    **{f'{x}_hinge{i + 1}': x for x in ('v', 'w') for i in range(len(KNOTS))},
    **{_bump_name(x, i, j): 'v*w' for x in ('v', 'w') for i in range(len(BUMP_CENTRES))
       for j in range(len(BUMP_CENTRES))}}
# The diagnosis trace signal that shows each input group.
INPUT_SIGNALS: dict[str, str] = {'v': 'body_speed', 'w': 'yaw_rate', 'v*w': 'v_omega',
                                 'dv': 'd_body_speed', 'dw': 'd_yaw_rate', 'turn': 'curvature'}
_FUNCTIONS = tuple(fn for _, _, fn, _ in TERMS)


def term_names(level: int | None = None) -> tuple[str, ...]:
    """Return the library's term names up to ``level`` (None: all)."""
    return tuple(name for name, lvl, _, _ in TERMS if level is None or lvl <= level)


def coefficient_names() -> tuple[str, ...]:
    """Return the coefficient parameter names, output-major: vx_v, vx_w, ..., wz_v_w2."""
    return tuple(f'{out}_{term}' for out, _ in OUTPUTS for term, _, _, _ in TERMS)


def range_names() -> tuple[str, ...]:
    """Return the fitted-range parameter names: v_lo, v_hi, w_lo, ..."""
    return tuple(f'{name}_{side}' for name, _, _ in INPUTS for side in ('lo', 'hi'))


def input_values(twist: np.ndarray, rate: np.ndarray | None) -> tuple[np.ndarray, ...]:
    """Return the raw inputs (v, w, dv, dw) of base twists (..., 3) and their rates."""
    twist = np.asarray(twist, dtype=float)
    rate = np.zeros(twist.shape) if rate is None else np.asarray(rate, dtype=float)
    return twist[..., 0], twist[..., 2], rate[..., 0], rate[..., 2]


def _scaled(x, lo: float, hi: float):
    """Clamp to [lo, hi] and divide by the range's largest magnitude (0 for an empty range)."""
    scale = max(abs(lo), abs(hi))
    if not scale > 0.0:
        return x * 0.0
    if isinstance(x, np.ndarray):
        return np.minimum(np.maximum(x, lo), hi) / scale
    return min(max(x, lo), hi) / scale


def features(ranges: Sequence[float], twist: np.ndarray, rate: np.ndarray | None,
             terms: Sequence[int] | None = None) -> np.ndarray:
    """Return the library terms (..., T) of base twists and rates, inputs clamped and scaled.

    ``ranges``: (v_lo, v_hi, w_lo, w_hi, dv_lo, dv_hi, dw_lo, dw_hi); ``terms``: only these
    terms are computed (by index; the others are 0), None: all.
    """
    raw = input_values(twist, rate)
    scaled = [_scaled(np.asarray(x, dtype=float), ranges[2 * i], ranges[2 * i + 1])
              for i, x in enumerate(raw)]
    shape = np.shape(scaled[0])
    if terms is not None:
        out = np.zeros(shape + (len(TERMS),))
        for j in terms:
            out[..., j] = _FUNCTIONS[j](*scaled)
        return out
    return np.stack([np.broadcast_to(np.asarray(fn(*scaled), dtype=float), shape)
                     for fn in _FUNCTIONS], axis=-1)


def _scaled_partials(x: np.ndarray, lo: float, hi: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return d _scaled / d (x, lo, hi): the slope inside the range, the edges' outside it."""
    scale = max(abs(lo), abs(hi))
    if not scale > 0.0:
        zero = np.zeros(np.shape(x))
        return zero, zero, zero
    clamped = np.minimum(np.maximum(x, lo), hi)
    d_x = np.where((x > lo) & (x < hi), 1.0 / scale, 0.0)
    # the scale follows the larger magnitude of the two edges
    d_scale_lo = np.sign(lo) if abs(lo) >= abs(hi) else 0.0
    d_scale_hi = np.sign(hi) if abs(hi) > abs(lo) else 0.0
    d_lo = np.where(x <= lo, 1.0 / scale, 0.0) - clamped / scale ** 2 * d_scale_lo
    d_hi = np.where(x >= hi, 1.0 / scale, 0.0) - clamped / scale ** 2 * d_scale_hi
    return d_x, d_lo, d_hi


def _scaled_inputs(ranges: Sequence[float], twist: np.ndarray, rate: np.ndarray | None
                   ) -> tuple[list[np.ndarray], list[tuple]]:
    """Return each input clamped and scaled, and its :func:`_scaled_partials`."""
    scaled, slopes = [], []
    for i, x in enumerate(input_values(twist, rate)):
        x = np.asarray(x, dtype=float)
        lo, hi = ranges[2 * i], ranges[2 * i + 1]
        scaled.append(_scaled(x, lo, hi))
        slopes.append(_scaled_partials(x, lo, hi))
    return scaled, slopes


def feature_gradients(ranges: Sequence[float], twist: np.ndarray, rate: np.ndarray | None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Return the terms' derivatives, d phi / d (v, w, dv, dw) and d phi / d ranges.

    Shapes (..., T, 4) and (..., T, 8), from :data:`TERM_GRADIENTS` and the clamp-and-scale of
    each input.
    """
    scaled, slopes = _scaled_inputs(ranges, twist, rate)
    shape = np.shape(scaled[0])
    d_scaled = np.stack([np.stack([np.broadcast_to(np.asarray(g, dtype=float), shape)
                                   for g in TERM_GRADIENTS[name](*scaled)], axis=-1)
                         for name, _, _, _ in TERMS], axis=-2)  # (..., T, 4)
    d_inputs = d_scaled * np.stack([s[0] for s in slopes], axis=-1)[..., None, :]
    d_ranges = np.zeros(shape + (len(TERMS), 2 * len(INPUTS)))
    for i, (_, d_lo, d_hi) in enumerate(slopes):
        d_ranges[..., 2 * i] = d_scaled[..., i] * d_lo[..., None]
        d_ranges[..., 2 * i + 1] = d_scaled[..., i] * d_hi[..., None]
    return d_inputs, d_ranges


def correction_gradient(coef: np.ndarray, ranges: Sequence[float], twist: np.ndarray,
                        rate: np.ndarray | None) -> np.ndarray:
    """Return d (C phi) / d (v, w, dv, dw) (..., O, 4) for coefficients ``coef`` (O, T).

    :func:`feature_gradients` contracted with the coefficients term by term, skipping the terms
    no output uses (above the chosen level every coefficient is 0): the fits need only this.
    """
    scaled, slopes = _scaled_inputs(ranges, twist, rate)
    slopes = [slope[0] for slope in slopes]
    shape = np.shape(scaled[0])
    out = np.zeros(shape + (len(coef), len(INPUTS)))
    for t, (name, _, _, _) in enumerate(TERMS):
        used = [o for o in range(len(coef)) if coef[o][t] != 0.0]
        if not used:
            continue
        for i, slope in enumerate(TERM_GRADIENTS[name](*scaled)):
            if np.ndim(slope) == 0 and slope == 0.0:
                continue
            part = slope * slopes[i]
            for o in used:
                out[..., o, i] += coef[o][t] * part
    return out


def scalar_features(ranges: Sequence[float], v: float, w: float, dv: float, dw: float
                    ) -> tuple[float, ...]:
    """:func:`features` for one sample on plain floats."""
    p = _scaled(v, ranges[0], ranges[1])
    q = _scaled(w, ranges[2], ranges[3])
    a = _scaled(dv, ranges[4], ranges[5])
    b = _scaled(dw, ranges[6], ranges[7])
    return tuple(fn(p, q, a, b) for fn in _FUNCTIONS)


def correction(coef: Sequence[float], phi: np.ndarray,
               terms: Sequence[int] | None = None) -> np.ndarray:
    """Return C phi (..., 3): each output's terms summed in library order (no BLAS).

    The terms are read from one contiguous copy, term by term (a strided term is slower to
    read), and summed in place: the same operations in the same order. ``terms``: only these
    (increasing; every term with a non-zero coefficient among them, :func:`used_terms`): a
    term left out adds 0.0, so the sum is the full one's bit for bit (up to the sign of an
    exact zero), as :func:`scalar_planned_correction` has it.
    """
    count = len(TERMS)
    phi = np.asarray(phi, dtype=float)
    used = list(range(count)) if terms is None else list(terms)
    if not used:
        return np.zeros(phi.shape[:-1] + (len(OUTPUTS),))
    columns = np.ascontiguousarray(np.moveaxis(phi if terms is None else phi[..., used], -1, 0))
    out = np.empty(columns.shape[1:] + (len(OUTPUTS),))
    part = np.empty(columns.shape[1:])
    for o in range(len(OUTPUTS)):
        total = np.multiply(columns[0], coef[o * count + used[0]], out=np.empty(part.shape))
        for n, j in enumerate(used[1:], 1):
            np.multiply(columns[n], coef[o * count + j], out=part)
            np.add(total, part, out=total)
        out[..., o] = total
    return out


def used_terms(coef: Sequence[float]) -> tuple[int, ...]:
    """Return the indices of the terms with a non-zero coefficient for some output."""
    matrix = np.asarray(coef, dtype=float).reshape(len(OUTPUTS), len(TERMS))
    return tuple(np.flatnonzero(np.any(matrix != 0.0, axis=0)).tolist())


def scalar_correction(coef: Sequence[float], phi: Sequence[float]) -> tuple[float, float, float]:
    """:func:`correction` for one sample on plain floats, in the same order."""
    count = len(TERMS)
    out = []
    for o in range(len(OUTPUTS)):
        total = phi[0] * coef[o * count]
        for j in range(1, count):
            total = total + phi[j] * coef[o * count + j]
        out.append(total)
    return out[0], out[1], out[2]


# The libraries of files written before today's one (same names, these orders): the 20-term one
def scalar_terms(ranges: Sequence[float], v: float, w: float, dv: float, dw: float,
                 terms: Sequence[int]) -> dict[int, float]:
    """:func:`scalar_features` of the given terms only, by term index."""
    p = _scaled(v, ranges[0], ranges[1])
    q = _scaled(w, ranges[2], ranges[3])
    a = _scaled(dv, ranges[4], ranges[5])
    b = _scaled(dw, ranges[6], ranges[7])
    return {j: _FUNCTIONS[j](p, q, a, b) for j in terms}


def correction_plan(coef: Sequence[float]) -> tuple[tuple[int, ...],
                                                    tuple[tuple[tuple[int, float], ...], ...]]:
    """Return the terms with a non-zero coefficient and, per output, its (term, coefficient).

    A file below the top level, or fitted sparse, leaves most of the library at 0: the node's
    per-sample form (:func:`scalar_planned_correction`) evaluates only these terms.
    """
    count = len(TERMS)
    outputs = tuple(tuple((j, float(coef[o * count + j])) for j in range(count)
                          if coef[o * count + j] != 0.0) for o in range(len(OUTPUTS)))
    return tuple(sorted({j for pairs in outputs for j, _ in pairs})), outputs


def scalar_planned_correction(plan: tuple[tuple[int, ...],
                                          tuple[tuple[tuple[int, float], ...], ...]],
                              ranges: Sequence[float], v: float, w: float, dv: float, dw: float
                              ) -> tuple[float, float, float]:
    """:func:`scalar_correction` of :func:`scalar_features` over the terms in use only.

    The same products summed in the same (library) order: a term left out adds 0.0, which
    leaves a sum unchanged, so the result is the full sum's bit for bit (up to the sign of
    an exact zero).
    """
    terms, outputs = plan
    phi = scalar_terms(ranges, v, w, dv, dw, terms)
    out = []
    for pairs in outputs:
        total = 0.0
        for j, c in pairs:
            total = total + phi[j] * c
        out.append(total)
    return out[0], out[1], out[2]


# (60 coefficients) and the 40-term one (120; today's without the bumps of level 7).
LEGACY_TERMS: tuple[str, ...] = (
    'v', 'w', 'abs_v', 'abs_w', 'v_abs_v', 'w_abs_w', 'v_w', 'v_abs_w', 'w_abs_v', 'abs_v_abs_w',
    'sign_v', 'sign_w', 'dv', 'dw', 'dv_up', 'dw_up', 'v3', 'w3', 'v2_w', 'v_w2')
LEGACY_LAYOUTS: tuple[tuple[str, ...], ...] = (
    LEGACY_TERMS, tuple(name for name, level, _, _ in TERMS if level <= 6))


def upgrade_covariance(flat: Sequence[float]) -> list[float] | None:
    """Return an earlier library's coefficient covariance placed in today's layout, else None.

    The coefficients are read by name, so an earlier file's values load as they are (the new
    terms default to 0); only its covariance, a flat list in the earlier order (60 x 60 or
    120 x 120), needs moving.
    """
    for terms in LEGACY_LAYOUTS:
        legacy = len(OUTPUTS) * len(terms)
        if len(flat) != legacy * legacy:
            continue
        names = coefficient_names()
        index = [names.index(f'{out}_{term}') for out, _ in OUTPUTS for term in terms]
        matrix = np.zeros((len(names), len(names)))
        matrix[np.ix_(index, index)] = np.asarray(flat, dtype=float).reshape(legacy, legacy)
        return matrix.ravel().tolist()
    return None
