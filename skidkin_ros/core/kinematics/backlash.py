"""Drivetrain backlash: the wheel follows its motor (where the encoder is) with a play.

After a wheel reverses, its motor turns through the play before the wheel moves again: the
encoder counts motion the ground never sees. No function of the present wheel speeds can say
this; it depends on how far each wheel has turned since it last reversed. The ``backlash``
extension carries that history as a state per wheel, the deficit d = wheel angle - motor
angle, which the play keeps in [-h, h] (h = play / 2, in rad of the wheel):

1. at each wheel sample, the motion of the interval just ended moves the deficit, exactly as
   the play does: d <- clamp(d - u_prev dt, -h, h) (u_prev: the encoder speed held over it);
2. over the interval that begins, the wheel turns only once the motor has crossed the gap to
   the engaging edge (d + h when driving forward, h - d backward); with the interval as long as
   the last one (dt_prev), the mean speed is u (1 - gap / (|u| dt_prev)) when the motor
   crosses the gap within it, u when it is engaged already, 0 when it stays inside the play.
   For a constant sample period this is the exact mean of the play's output; otherwise the
   error is at most the part of one interval in which the wheel engages, and it never
   accumulates (step 1 follows the motor exactly);
3. the state starts centred (d = 0, nothing known of the last interval) on the first sample
   and after a gap; a repeated stamp moves nothing.

The node's per-sample form (:func:`play_step`) and the batch form (:func:`play_speeds`, a loop
over the samples, every row at once) do the same operations in the same order, so the node and
``skidkin predict`` agree bit for bit; the batch form also gives the derivative by h (the fits'
exact Jacobian).
"""

from __future__ import annotations

import numpy as np

__all__ = ['play_step', 'play_speeds', 'PLAY_STATE']

# (deficit left, deficit right, speed left, speed right, last step s) before any sample.
PLAY_STATE: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)


def _mean_speed(u: float, d: float, h: float, last_s: float) -> float:
    """Return the wheel's mean speed over the coming interval (step 2 of the module)."""
    gap = d + h if u > 0.0 else (h - d if u < 0.0 else 0.0)
    if not gap > 0.0:
        return u
    travel = abs(u) * last_s
    return u * (1.0 - gap / travel) if travel > gap else 0.0


def play_step(state: tuple[float, float, float, float, float], half_play: float,
              step_s: float, restart: bool, omega_l: float, omega_r: float
              ) -> tuple[tuple[float, float, float, float, float], float, float]:
    """Take one wheel sample on plain floats; return the new state and the wheels' speeds.

    ``state``: :data:`PLAY_STATE` or what the previous call returned; ``step_s``: the time since
    the previous sample (ignored with ``restart``, the first sample or after a gap).
    """
    d_l, d_r, u_l, u_r, last_s = state
    if restart:
        d_l, d_r, last_s = 0.0, 0.0, 0.0
    elif step_s > 0.0:
        d_l = min(max(d_l - u_l * step_s, -half_play), half_play)
        d_r = min(max(d_r - u_r * step_s, -half_play), half_play)
        last_s = step_s
    left = _mean_speed(omega_l, d_l, half_play, last_s)
    right = _mean_speed(omega_r, d_r, half_play, last_s)
    return (d_l, d_r, omega_l, omega_r, last_s), left, right


def _row(omega: list, dt_s: list, restart: list, h: float) -> tuple[list, list]:
    """:func:`play_step` along one row on plain floats, with the slope by h (forward mode).

    ``restart``: with the first sample marked; ``dt_s``: the step that ends at each sample
    (its first entry unused).
    """
    speed, speed_by_h = [], []
    put, put_by_h = speed.append, speed_by_h.append
    d = d_by_h = last_s = u_prev = 0.0
    for u, step, again in zip(omega, dt_s, restart):
        if again:
            d, d_by_h, last_s = 0.0, 0.0, 0.0
        elif step > 0.0:
            free = d - u_prev * step
            if free < -h:
                d, d_by_h = -h, -1.0
            elif free > h:
                d, d_by_h = h, 1.0
            else:
                d = free
            last_s = step
        if u > 0.0:
            gap, gap_by_h = d + h, d_by_h + 1.0
        elif u < 0.0:
            gap, gap_by_h = h - d, 1.0 - d_by_h
        else:
            gap, gap_by_h = 0.0, 0.0
        if not gap > 0.0:
            put(u)
            put_by_h(0.0)
        else:
            travel = abs(u) * last_s
            if travel > gap:
                put(u * (1.0 - gap / travel))
                put_by_h(-u * gap_by_h / travel)
            else:
                put(0.0)
                put_by_h(0.0)
        u_prev = u
    return speed, speed_by_h


# The last few results of play_speeds with copies of their inputs: a fit asks for the same
# speeds at the same play again (its Jacobian after its evaluation, every fold at the start
# value). Comparing the inputs costs a pass over them, the loop a microsecond a sample.
_RECENT: list[tuple[float, np.ndarray, np.ndarray, np.ndarray,
                    tuple[np.ndarray, np.ndarray]]] = []
_RECENT_SIZE = 8
_RECENT_BYTES = 64 << 20  # what the kept inputs and results may take in all


def play_speeds(omega: np.ndarray, dt_s: np.ndarray, restart: np.ndarray, half_play: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Return the wheel speeds of encoder speeds ``omega`` (D, L) and their derivative by h.

    ``dt_s[:, i]``: the step from sample i to i + 1 (0 across a gap or at a repeated stamp);
    ``restart[:, i]``: sample i starts afresh. :func:`play_step`'s operations row by row on
    plain floats (a sample loop: on floats it costs about a microsecond a sample, a tenth of
    the same loop on arrays of a few rows). The same arrays at the same play give the same
    (read-only) result arrays again, without the loop.
    """
    h = float(half_play)
    values = np.asarray(omega, dtype=float)
    steps = np.asarray(dt_s, dtype=float)
    starts = np.asarray(restart, dtype=bool)
    for known_h, known_omega, known_dt, known_restart, known in _RECENT:
        if (known_h == h and np.array_equal(known_omega, values)
                and np.array_equal(known_dt, steps) and np.array_equal(known_restart, starts)):
            return known
    out = np.empty_like(values)
    out_by_h = np.empty_like(values)
    # the step that ends at each sample, and the restarts with every row's first sample
    ending = np.zeros(values.shape)
    ending[:, 1:] = steps[:, :values.shape[1] - 1]
    again = starts.copy()
    again[:, :1] = True
    ending_rows, again_rows = ending.tolist(), again.tolist()
    for r, row in enumerate(values.tolist()):
        out[r], out_by_h[r] = _row(row, ending_rows[r], again_rows[r], h)
    out.flags.writeable = False
    out_by_h.flags.writeable = False
    result = (out, out_by_h)
    _RECENT.insert(0, (h, values.copy(), steps.copy(), starts.copy(), result))
    del _RECENT[_RECENT_SIZE:]
    while _RECENT and sum(_kept_bytes(entry) for entry in _RECENT) > _RECENT_BYTES:
        _RECENT.pop()
    return result


def _kept_bytes(entry: tuple) -> int:
    _, omega, dt_s, restart, (out, out_by_h) = entry
    return omega.nbytes + dt_s.nbytes + restart.nbytes + out.nbytes + out_by_h.nbytes
