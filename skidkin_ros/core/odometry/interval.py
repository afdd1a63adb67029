"""The sample-interval convention: which wheel speeds drive the robot between two samples.

A wheel sample k (stamp t_k, speeds omega_k) is one number per side for a stretch of time; the
convention says which stretch. The integrator moves the robot over [t_{k-1}, t_k] with

- ``ending`` (the default): omega_k, the newest measurement, over the interval that ends at its
  stamp. This is what diff_drive_controller does (it integrates each new reading, or the
  difference of encoder positions, over the time since the last one), and what a speed computed
  from encoder positions means (travel over [t_{k-1}, t_k] divided by its length);
- ``starting``: omega_{k-1} held until the next sample arrives (a zero-order hold from the
  stamp on). The pose published at t_k then lags by half a sample; skidkin_ros before the
  convention existed did this, and a parameters file calibrated then keeps meaning it
  (:data:`LEGACY_INTERVAL`);
- ``midpoint``: (omega_{k-1} + omega_k) / 2, the trapezoid rule on each wheel's angle.

Every path uses these rules through this module: the streaming integrator (the node and
``skidkin predict``) combines the previous and the new sample with :func:`interval_speed`, and
the batch tools (segments, the segment predictor, the diagnosis) first turn a drive's samples
into the speeds *held* from each stamp to the next (:func:`held_wheels`), after which the same
zero-order hold as ever applies. Both give the same numbers, bit for bit.
"""

from __future__ import annotations

import numpy as np

from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.errors import ParameterError

__all__ = ['INTERVALS', 'DEFAULT_INTERVAL', 'LEGACY_INTERVAL', 'check_interval',
           'interval_speed', 'held_speeds', 'held_wheels']

INTERVALS = ('ending', 'starting', 'midpoint')
DEFAULT_INTERVAL = 'ending'
# What a parameters file written by a calibration without an ``interval`` entry means.
LEGACY_INTERVAL = 'starting'


def check_interval(value: object) -> str:
    """Return a valid convention name, or raise ParameterError naming the choices."""
    if not isinstance(value, str) or value not in INTERVALS:
        raise ParameterError(f'interval must be one of {", ".join(INTERVALS)} (which interval a '
                             f'wheel sample describes), got {value!r}')
    return value


def interval_speed(before: float, after: float, interval: str) -> float:
    """Return the speed integrated between a sample (``before``) and the next (``after``)."""
    if interval == 'ending':
        return after
    if interval == 'midpoint':
        return (before + after) * 0.5
    return before


def held_speeds(omega: np.ndarray, interval: str) -> np.ndarray:
    """Return the speeds held from each stamp to the next, along the last axis.

    Slot i holds :func:`interval_speed` (omega_i, omega_{i+1}); the last slot (held past the last
    stamp, never integrated by the node) keeps its own sample.
    """
    omega = np.asarray(omega, dtype=float)
    if interval == 'starting' or omega.shape[-1] < 2:
        return omega
    held = omega.copy()
    if interval == 'ending':
        held[..., :-1] = omega[..., 1:]
    else:
        held[..., :-1] = (omega[..., :-1] + omega[..., 1:]) * 0.5
    return held


def held_wheels(wheels: WheelSamples, interval: str) -> WheelSamples:
    """Return the samples with the speeds held from each stamp to the next (see the module)."""
    if interval == 'starting':
        return wheels
    return WheelSamples(wheels.t_ns, held_speeds(wheels.omega_l, interval),
                        held_speeds(wheels.omega_r, interval))
