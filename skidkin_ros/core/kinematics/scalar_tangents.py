"""Exact d twist / d k of an augmented model at one wheel sample, on plain floats.

The node carries the parameter uncertainty of a model learned online per wheel sample
(:class:`~skidkin_ros.core.online.augmented.LayoutUncertainty`): it needs the derivative of the
twist by every learned parameter at each step. Central differences cost two evaluations of the
whole augmented twist per parameter (16 for eight parameters; with a residual model each
evaluates its library terms). This module gives the same derivative exactly, in forward mode
on floats, in one pass: the base model's gradient (:meth:`KinematicModel.rows_gradient`, linear
base models only) at the wheel speeds and at their rate, carried through each twist-stage
extension by its partials on floats (the float twins of
:meth:`~skidkin_ros.core.kinematics.extensions.Extension.partials`, same branches; the
residual model's terms' slopes are :data:`~skidkin_ros.core.kinematics.residual.TERM_GRADIENTS`,
the fits' own). ``test_scalar_tangents.py`` checks every entry against the array partials and
against central differences on random inputs.

Covered: the extensions learned online whose parameters are all free or held
(:data:`SCALAR_PARTIALS`), the residual model with only its gains free. Anything else
(a ROC base, a free coefficient or range of the residual model, an extension without a float
partial): :func:`scalar_tangents` returns None and the caller keeps the central differences.
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

from skidkin_ros.core.kinematics import residual
from skidkin_ros.core.kinematics.augmented import BoundAugmented
from skidkin_ros.core.kinematics.extensions import (_RESIDUAL_COEFS, _RESIDUAL_GAINS,
                                                    _RESIDUAL_RANGES, get_extension,
                                                    MAX_SPEED_SLIP, SLIP_LEVER_M)

__all__ = ['ScalarTangents', 'scalar_tangents', 'SCALAR_PARTIALS']

Triple = tuple[float, float, float]
# One extension's float partials: (k, twist in, wheel speeds, rate, tangents, rate tangents,
# own columns, what PREPARE made of k once) -> None. ``tangents``: per parameter column,
# [d vx, d vy, d w] of the twist in, updated in place to the twist out's (chain rule, then the
# extension's own parameters' slopes added in their columns: ``own`` = (column, parameter
# index) pairs).
Partial = Callable[..., None]


def _speed_slip(k, x, wl, wr, rate, tangents, rate_tangents, own, prep):
    vx = x[0]
    inside = k[0] * abs(vx) < MAX_SPEED_SLIP
    factor = 1.0 - 2.0 * k[0] * abs(vx) if inside else 1.0 - MAX_SPEED_SLIP
    for t in tangents:
        t[0] = factor * t[0]
    for c, _ in own:
        tangents[c][0] += -vx * abs(vx) if inside else 0.0


def _direction_asymmetry(k, x, wl, wr, rate, tangents, rate_tangents, own, prep):
    vx = x[0]
    ratio = -vx / k[1]
    reverse = min(max(ratio, 0.0), 1.0)
    inside = 0.0 < ratio < 1.0
    factor = 1.0 - k[0] * reverse + (vx * k[0] / k[1] if inside else 0.0)
    for t in tangents:
        t[0] = factor * t[0]
    for c, j in own:
        if j == 0:
            tangents[c][0] += -vx * reverse
        elif inside:
            tangents[c][0] += -vx * k[0] * vx / k[1] ** 2


def _lateral_skid(k, x, wl, wr, rate, tangents, rate_tangents, own, prep):
    vx, _, w = x
    for t in tangents:
        t[1] = t[1] + k[0] * w * t[0] + k[0] * vx * t[2]
    for c, _ in own:
        tangents[c][1] += vx * w


def _icr_offset(k, x, wl, wr, rate, tangents, rate_tangents, own, prep):
    for t in tangents:
        t[1] = t[1] + k[0] * t[2]
    for c, _ in own:
        tangents[c][1] += x[2]


def _ratio_yaw_slip(k, x, wl, wr, rate, tangents, rate_tangents, own, prep):
    big = max(abs(wl), abs(wr))
    small = min(abs(wl), abs(wr))
    ratio = small / big if (wl * wr) > 0.0 and big > 0.0 else -1.0
    q = (ratio - k[1]) / k[2]
    bump = float(np.exp(-(q * q)))   # the float form's exp
    factor = 1.0 - k[0] * bump
    for t in tangents:
        t[2] = factor * t[2]
    w = x[2]
    for c, j in own:
        if j == 0:
            tangents[c][2] += -w * bump
        elif j == 1:
            tangents[c][2] += -w * k[0] * bump * 2.0 * q / k[2]
        else:
            tangents[c][2] += -w * k[0] * bump * 2.0 * q * q / k[2]


def _acceleration_slip(k, x, wl, wr, rate, tangents, rate_tangents, own, prep):
    vx = x[0]
    dv = rate[0]
    up = dv if vx * dv > 0.0 else 0.0
    slipping = k[0] * abs(up) < abs(vx)
    by_rate = -k[0] if slipping and up != 0.0 else 0.0
    for t, r in zip(tangents, rate_tangents):
        t[0] = (t[0] if slipping else 0.0) + by_rate * r[0]
    for c, _ in own:
        tangents[c][0] += -math.copysign(1.0, vx) * abs(up) if slipping else 0.0


_TERM_VALUES = tuple(function for _, _, function, _ in residual.TERMS)
_TERM_SLOPES = tuple(residual.TERM_GRADIENTS[name] for name, _, _, _ in residual.TERMS)


def _scaled_slope(x: float, lo: float, hi: float) -> tuple[float, float]:
    """Return (clamped and scaled x, its slope by x): residual._scaled and its derivative."""
    scale = max(abs(lo), abs(hi))
    if not scale > 0.0:
        return x * 0.0, 0.0
    return min(max(x, lo), hi) / scale, (1.0 / scale if lo < x < hi else 0.0)


def _sign(x: float) -> float:
    return 1.0 if x > 0.0 else (-1.0 if x < 0.0 else 0.0)


def _residual_model(k, x, wl, wr, rate, tangents, rate_tangents, own, prep):
    """Carry the tangents through the residual model (gains free; coefficients, ranges held)."""
    terms, outputs = prep
    ranges = k[_RESIDUAL_COEFS:_RESIDUAL_COEFS + _RESIDUAL_RANGES]
    vx, _, w = x
    p, sp = _scaled_slope(vx, ranges[0], ranges[1])
    q, sq = _scaled_slope(w, ranges[2], ranges[3])
    a, sa = _scaled_slope(rate[0], ranges[4], ranges[5])
    b, sb = _scaled_slope(rate[2], ranges[6], ranges[7])
    phi, slopes = {}, {}
    for j in terms:
        phi[j] = _TERM_VALUES[j](p, q, a, b)
        g = _TERM_SLOPES[j](p, q, a, b)
        slopes[j] = (float(g[0]) * sp, float(g[1]) * sq, float(g[2]) * sa, float(g[3]) * sb)
    gains = k[_RESIDUAL_GAINS:_RESIDUAL_GAINS + 3]
    v_abs, w_abs = abs(vx), abs(w)
    linear = v_abs + w_abs * SLIP_LEVER_M
    angular = w_abs + v_abs / SLIP_LEVER_M
    sv, sw = _sign(vx), _sign(w)
    # per output with a term in use: (output, d/dv, d/dw of the twist, d/ddv, d/ddw of the
    # rate), and its slope by its gain (the correction before the gain; 0 when clipped)
    rows, by_gain = [], [0.0, 0.0, 0.0]
    for o, pairs in enumerate(outputs):
        if not pairs:
            continue
        raw = 0.0
        for j, c in pairs:   # scalar_planned_correction's sum
            raw = raw + phi[j] * c
        change = raw * gains[o]
        bound = angular if o == 2 else linear
        if change > bound or change < -bound:
            side = 1.0 if change > bound else -1.0
            if o == 2:
                rows.append((o, side * sv / SLIP_LEVER_M, side * sw, 0.0, 0.0))
            else:
                rows.append((o, side * sv, side * sw * SLIP_LEVER_M, 0.0, 0.0))
            continue
        dv = dw = ddv = ddw = 0.0
        for j, c in pairs:
            s = slopes[j]
            dv += c * s[0]
            dw += c * s[1]
            ddv += c * s[2]
            ddw += c * s[3]
        g = gains[o]
        rows.append((o, g * dv, g * dw, g * ddv, g * ddw))
        by_gain[o] = raw
    for t, r in zip(tangents, rate_tangents):
        t0, t2, r0, r2 = t[0], t[2], r[0], r[2]
        for o, dv, dw, ddv, ddw in rows:
            t[o] = t[o] + dv * t0 + dw * t2 + ddv * r0 + ddw * r2
    for c, j in own:
        o = j - _RESIDUAL_GAINS
        tangents[c][o] += by_gain[o]


# What a partial needs of its values, made once per bound model (the residual model's terms in
# use: the plan its float form evaluates).
PREPARE: dict[str, Callable] = {
    'residual_model': lambda k: residual.correction_plan(k[:_RESIDUAL_COEFS]),
}

SCALAR_PARTIALS: dict[str, Partial] = {
    'speed_slip': _speed_slip,
    'direction_asymmetry': _direction_asymmetry,
    'lateral_skid': _lateral_skid,
    'icr_offset': _icr_offset,
    'ratio_yaw_slip': _ratio_yaw_slip,
    'acceleration_slip': _acceleration_slip,
    'residual_model': _residual_model,
}


class ScalarTangents:
    """d twist / d k of one bound augmented model, per sample on floats (module docstring)."""

    def __init__(self, bound: BoundAugmented, free: Sequence[tuple[int, int]],
                 base_rows: tuple[tuple[float, ...], ...]) -> None:
        self.bound = bound
        self.size = len(free)
        # per base column: (column, d rows / dk_j as 6 floats)
        self._base = tuple((c, base_rows[j]) for c, (i, j) in enumerate(free) if i < 0)
        chain = []
        for index, (name, k) in enumerate(zip(bound.extensions, bound.values)):
            apply = get_extension(name).scalar_apply()
            own = tuple((c, j) for c, (i, j) in enumerate(free) if i == index)
            values = tuple(np.asarray(k, float).tolist())
            prepare = PREPARE.get(name)
            chain.append((apply, SCALAR_PARTIALS[name], values, own,
                          None if prepare is None else prepare(values)))
        self._chain = tuple(chain)

    def jacobian(self, left: float, right: float, rate_l: float = 0.0, rate_r: float = 0.0
                 ) -> list[Triple]:
        """Return d twist / d k_j (d vx, d vy, d w) for every column j at these wheel speeds.

        ``rate_l``, ``rate_r``: the wheel speeds' rate (the base twist's rate is the base
        model's map of them); the twist is the memoryless one at t = 0, as
        :meth:`BoundAugmented.scalar_memoryless` gives it with that rate.
        """
        tangents = [[0.0, 0.0, 0.0] for _ in range(self.size)]
        rate_tangents = [[0.0, 0.0, 0.0] for _ in range(self.size)]
        for c, (a, b, cc, d, e, f) in self._base:
            tangents[c] = [left * a + right * b, left * cc + right * d, left * e + right * f]
            rate_tangents[c] = [rate_l * a + rate_r * b, rate_l * cc + rate_r * d,
                                rate_l * e + rate_r * f]
        base = self.bound.base
        x = base.scalar_twist(left, right)
        rate = base.scalar_twist(rate_l, rate_r) if rate_l or rate_r else (0.0, 0.0, 0.0)
        last = len(self._chain) - 1
        for n, (apply, partial, k, own, prep) in enumerate(self._chain):
            partial(k, x, left, right, rate, tangents, rate_tangents, own, prep)
            if n < last:   # the twist out of the last extension is not needed
                x = apply(k, x[0], x[1], x[2], left, right, 0.0, rate)
        return [(t[0], t[1], t[2]) for t in tangents]


def scalar_tangents(bound: BoundAugmented, free: Sequence[tuple[int, int]]
                    ) -> ScalarTangents | None:
    """Return the exact float tangents of ``bound`` by ``free``, None where not covered."""
    grad = bound.base.model.rows_gradient(bound.base.k, bound.base.geometry)
    if grad is None:
        return None
    for index, name in enumerate(bound.extensions):
        if name not in SCALAR_PARTIALS:
            return None
        if name == 'residual_model' and any(i == index and j < _RESIDUAL_GAINS
                                            for i, j in free):
            return None
    rows = tuple(tuple(np.asarray(g, dtype=float).ravel().tolist()) for g in grad)
    return ScalarTangents(bound, free, rows)
