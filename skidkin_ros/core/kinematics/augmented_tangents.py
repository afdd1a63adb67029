"""Exact (forward-mode) derivatives of an augmented model's batch twists, for the fits.

:func:`interval_tangents` gives :meth:`BoundAugmented.intervals`' mean twists and their
derivatives with respect to the free parameters (the base model's and the extensions'), from the
base model's gradient (:func:`base_tangents`), each extension's partials (beside its twist rule,
:meth:`~skidkin_ros.core.kinematics.extensions.Extension.partials`) and the lags' recursion. The
fits (:mod:`skidkin_ros.core.calibration.predictor`, :mod:`~skidkin_ros.core.calibration.fitting`)
use them; ``test_jacobians.py`` checks them against central differences. The node never needs
them: they live apart from the rollout they differentiate (:mod:`.augmented`).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from skidkin_ros.core.kinematics.augmented import (BoundAugmented, first_order_response,
                                                   lag_factors, lag_response, rate_steps,
                                                   twist_rates)
from skidkin_ros.core.kinematics.backlash import play_speeds
from skidkin_ros.core.kinematics.extensions import get_extension
from skidkin_ros.core.kinematics.models import BoundModel
from skidkin_ros.core.scratch import scratch

__all__ = ['interval_tangents', 'base_tangents', 'chain_partials']


def interval_tangents(bound: BoundAugmented, t_ns: np.ndarray, omega_l: np.ndarray,
                      omega_r: np.ndarray, dt_s: np.ndarray, restart: np.ndarray,
                      free: Sequence[tuple[int, int]]
                      ) -> tuple[np.ndarray, list[np.ndarray]]:
    """:meth:`BoundAugmented.intervals`' mean twists (D, L, 3) and their exact derivatives.

    The derivatives come per twist component, each (P, D, L): one contiguous array per
    parameter, so each step is P plain array operations. ``free``: the P parameters, each
    (-1 for the base model or an extension's index, the parameter's index). Forward mode:
    the base twist's gradient, carried through the rate, each twist-stage extension
    (:meth:`Extension.partials`) and the lags (linear in their input; a time constant's own
    slope from the derivative of its recursion). A time offset moves the segment windows,
    not the twists: its slope is the predictor's.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    t_s = (t_ns - t_ns[:, :1]) * 1e-9
    omega_l = np.asarray(omega_l, dtype=float)
    omega_r = np.asarray(omega_r, dtype=float)
    omega_l, omega_r, play = _wheel_stage(bound, omega_l, omega_r, dt_s, restart, free)
    base = np.asarray(bound.base.twist(omega_l, omega_r), dtype=float)
    d_x = base_tangents(bound.base, omega_l, omega_r, free)
    for c, slope in play:
        for m in range(3):
            d_x[m][c] += slope[m]
    rate = d_rate = None
    x = base
    live = any(i < 0 for i, _ in free) or bool(play)  # whether a tangent is carried in yet
    for index, (name, k) in enumerate(zip(bound.extensions, bound.values)):
        ext = get_extension(name)
        if ext.stage != 'twist':
            continue
        if ext.uses_rate and rate is None:
            rate = twist_rates(base, dt_s, restart)
            d_rate = [_rate_tangents(d, dt_s, restart)
                      for d in base_tangents(bound.base, omega_l, omega_r, free, 'rate')]
            for c, slope in play:
                for m in range(3):
                    d_rate[m][c] += _rate_tangents(slope[m][None], dt_s, restart)[0]
        mine = [(c, j) for c, (i, j) in enumerate(free) if i == index]
        d_twist, d_by_rate, d_k = ext.partials(
            k, x, omega_l, omega_r, t_s, np.zeros(base.shape) if rate is None else rate,
            [j for _, j in mine], inputs=live)
        d_x, live = chain_partials((d_twist, d_by_rate, d_k), d_x, d_rate, mine, live)
        x = ext.apply(k, x, omega_l, omega_r, t_s, rate)
    taus = bound.taus
    lags = _free_lags(bound, free)
    if not max(taus) > 0.0 and not lags:
        return x, d_x
    mean = x.copy()
    dt_s = np.asarray(dt_s, dtype=float)
    restart = np.asarray(restart, bool)
    held = {}
    d_mean = list(d_x)
    for tau in sorted({t for t in taus if t > 0.0}):
        columns = [c for c in range(3) if taus[c] == tau]
        lagged, mean[..., columns] = lag_response(x[..., columns], dt_s, restart, tau)
        d, g = lag_factors(dt_s, tau)
        for n, c in enumerate(columns):
            held[c] = lagged[..., n]
            # the response is linear in its input: the tangents follow the same recursion;
            # a direction whose input tangent is 0 everywhere keeps 0 (its recursion is skipped)
            moving = [p for p in range(len(free)) if np.any(d_x[c][p])]
            d_mean[c] = np.zeros(np.shape(d_x[c]))
            if not moving:
                continue
            tangent = d_x[c][moving]
            d_held = first_order_response(tangent * (1.0 - d), d, dt_s, restart,
                                          tangent[..., 0], tangent)
            d_mean[c][moving] = tangent + (d_held - tangent) * g
    for c, columns, tau in lags:
        # the slope by the time constant itself; at tau = 0 the one-sided one (tau -> 0+)
        tau = max(tau, 1e-12)
        d, g = lag_factors(dt_s, tau)
        ratio = dt_s / tau
        d_by_tau = d * ratio / tau
        with np.errstate(over='ignore', invalid='ignore'):
            g_by_tau = np.where(ratio > 1e-4, -((ratio + 1.0) * d - 1.0) / (ratio * tau),
                                (0.5 - ratio / 3.0) * ratio / tau)
        g_by_tau = np.where(dt_s > 0.0, g_by_tau, 0.0)
        for m in columns:
            y = held.get(m) if taus[m] == tau else None
            if y is None:
                y = lag_response(x[..., m:m + 1], dt_s, restart, tau)[0][..., 0]
            gap = y - x[..., m]
            if not np.any(gap):  # a component that never moves: no slope by tau
                continue
            z = first_order_response((gap * d_by_tau)[None], d, dt_s, restart,
                                     np.zeros((1,) + gap.shape[:1]), None)[0]
            d_mean[m][c] += z * g + gap * g_by_tau
    return mean, d_mean


def _wheel_stage(bound: BoundAugmented, omega_l: np.ndarray, omega_r: np.ndarray,
                 dt_s: np.ndarray, restart: np.ndarray, free: Sequence[tuple[int, int]]
                 ) -> tuple[np.ndarray, np.ndarray, list[tuple[int, list[np.ndarray]]]]:
    """Return the wheels' speeds after the backlash and the base twist's slope by its play.

    Without a backlash the encoder speeds; the slope: (column in ``free``, d base twist /
    d play_rad per component) when the play is free.
    """
    half_play = bound.half_play
    if half_play is None:
        return omega_l, omega_r, []
    index = bound.extensions.index('backlash')
    left, left_by_h = play_speeds(omega_l, dt_s, restart, half_play)
    right, right_by_h = play_speeds(omega_r, dt_s, restart, half_play)
    columns = [c for c, (i, _) in enumerate(free) if i == index]
    if not columns:
        return left, right, []
    # d h / d play = 1/2; a linear base model maps the speeds' slope as it maps the speeds;
    # one that is not (ROC) by its central difference along that slope
    base = bound.base
    if base.model.rows(base.k, base.geometry) is not None:
        slope = np.asarray(base.twist(0.5 * left_by_h, 0.5 * right_by_h), dtype=float)
    else:
        step = 1e-6 * max(1.0, float(np.abs(left).max(initial=0.0)),
                          float(np.abs(right).max(initial=0.0)))
        up = np.asarray(base.twist(left + step * left_by_h, right + step * right_by_h))
        down = np.asarray(base.twist(left - step * left_by_h, right - step * right_by_h))
        slope = (up - down) / (4.0 * step)
    return left, right, [(c, [slope[..., m] for m in range(3)]) for c in columns]


def _free_lags(bound: BoundAugmented, free: Sequence[tuple[int, int]]
               ) -> list[tuple[int, list[int], float]]:
    """Return (column in ``free``, lagged twist components, tau) of each free time constant."""
    out = []
    for c, (i, j) in enumerate(free):
        if i < 0:
            continue
        ext = get_extension(bound.extensions[i])
        if ext.stage != 'dynamics':
            continue
        name = ext.param_names[j]
        columns = [m for m in range(3) if ext.lags[m] == name]
        out.append((c, columns, float(bound.values[i][j])))
    return out


def base_tangents(base: BoundModel, omega_l: np.ndarray, omega_r: np.ndarray,
                  free: Sequence[tuple[int, int]], work: str = 'base') -> list[np.ndarray]:
    """Return d (base twist) / d (free parameters) per component, each (P, ...).

    Only the base model's entries of ``free`` (index -1) have a slope here. ``work``: the
    name of the work array they are written in (:func:`scratch`: valid until the next call
    with that name).
    """
    out = scratch(work, (3, len(free)) + np.shape(omega_l))
    out[...] = 0.0
    columns = [(c, j) for c, (i, j) in enumerate(free) if i < 0]
    if not columns:
        return list(out)
    rows = base.model.rows_gradient(base.k, base.geometry)
    grad = None if rows is not None else base.model.twist_gradient(base.k, base.geometry,
                                                                   omega_l, omega_r)
    for c, j in columns:
        for m in range(3):
            if grad is not None:
                out[m, c] = grad[..., m, j]
            elif rows[j, m, 0] != 0.0 or rows[j, m, 1] != 0.0:
                np.multiply(omega_l, rows[j, m, 0], out=out[m, c])
                out[m, c] += omega_r * rows[j, m, 1]
    return list(out)


def _rate_tangents(tangent: np.ndarray, dt_s: np.ndarray, restart: np.ndarray) -> np.ndarray:
    """:func:`twist_rates` of tangents (P, D, L): the same backward difference, per direction."""
    rate = np.zeros(tangent.shape)
    usable, safe = rate_steps(dt_s, restart)
    rate[..., 1:] = np.where(usable, (tangent[..., 1:] - tangent[..., :-1]) / safe, 0.0)
    return rate


def chain_partials(partials: tuple, d_x: list[np.ndarray], d_rate: list[np.ndarray] | None,
                   mine: list[tuple[int, int]], live: bool) -> tuple[list[np.ndarray], bool]:
    """Carry the tangents d_x through one extension; return them and whether any is live.

    ``partials``: the extension's (d_twist, d_by_rate, d_k) (``Extension.partials``); ``mine``:
    (column, own parameter index) of its free parameters; ``live``: whether an earlier
    extension already made the tangents non-zero (before that, only d_k adds).
    """
    d_twist, d_by_rate, d_k = partials
    if live:
        d_x = _apply_partials(d_twist, d_x, d_by_rate, d_rate)
    for n, (c, _) in enumerate(mine):
        for m in range(3):
            d_x[m][c] += d_k[..., m, n]
    return d_x, live or bool(mine)


def _apply_partials(d_twist: np.ndarray | None, d_x: list[np.ndarray],
                    d_by_rate: np.ndarray | None, d_rate: list[np.ndarray] | None
                    ) -> list[np.ndarray]:
    """Return the tangents after one extension: d_twist @ d_x + d_by_rate @ d_rate, per row.

    Entries equal to the identity (or zero) everywhere are skipped: an extension moves one or
    two components, and the tangents are P times larger than the twist.
    """
    out = []
    for i in range(3):
        terms = []
        for j in range(3):
            if d_twist is None:
                if i == j:
                    terms.append((None, d_x[j]))
                continue
            entry = d_twist[..., i, j]
            if i == j and np.all(entry == 1.0):
                terms.append((None, d_x[j]))
            elif np.any(entry != 0.0):
                terms.append((entry, d_x[j]))
        if d_by_rate is not None:
            for j in range(3):
                entry = d_by_rate[..., i, j]
                if np.any(entry != 0.0):
                    terms.append((entry, d_rate[j]))
        total = None
        for entry, tangent in terms:
            part = tangent if entry is None else entry * tangent
            total = part if total is None else total + part
        out.append(np.zeros_like(d_x[i]) if total is None else total)
    return out
