"""Time units: one home for nanoseconds per second and the conversions between them.

Stamps are integer nanoseconds, as ROS and rosbags keep them; durations, periods and offsets in
the models and options are float seconds. The recipe, and why:

1. ``NS_PER_S`` is the one spelling of a second in nanoseconds. Composing or splitting a stamp
   (``sec * NS_PER_S + nanosec``, ``divmod(t_ns, NS_PER_S)``) is integer arithmetic and exact.
2. :func:`s_to_ns` makes integer nanoseconds of float seconds with one rounding rule: the float
   product ``seconds * 1e9`` rounded to the nearest integer, halves to even (what Python's
   ``round`` and ``numpy.round`` both do, so a scalar and an array give the same integers).
   Nearest, not truncation: a product such as ``1.001 * 1e9`` lands a hair below its integer
   (1000999999.9999999), and ``int()`` would drop a whole nanosecond from it.
3. :func:`s_to_ns_array` is the same rule for numpy arrays (int64).
4. :func:`ns_to_s` makes float seconds of nanoseconds (int, float or array) as ``t_ns * 1e-9``,
   the product the integrator and the calibration use, so every path gives the same bits.

A bound in seconds that is only compared with integer stamps (a tolerance, a timeout) may stay a
float, ``bound_s * NS_PER_S``: no rounding is involved, and an infinite bound stays infinite.
Float seconds carry about 16 significant digits: an absolute Unix time held in float seconds
resolves only about 0.2 us, so keep absolute stamps in integer nanoseconds and convert durations.
"""

from __future__ import annotations

import numpy as np

__all__ = ['NS_PER_S', 's_to_ns', 's_to_ns_array', 'ns_to_s']

NS_PER_S = 1_000_000_000


def s_to_ns(seconds: float) -> int:
    """Return float seconds as integer nanoseconds: nearest, halves to even.

    A non-finite value raises (ValueError for NaN, OverflowError for an infinity).
    """
    return int(round(seconds * NS_PER_S))


def s_to_ns_array(seconds: np.ndarray) -> np.ndarray:
    """Return float seconds as int64 nanoseconds, elementwise, with the rule of :func:`s_to_ns`."""
    return np.round(np.asarray(seconds, dtype=np.float64) * NS_PER_S).astype(np.int64)


def ns_to_s(t_ns: int | float | np.ndarray) -> float | np.ndarray:
    """Return nanoseconds (int, float or array) as float seconds (``t_ns * 1e-9``)."""
    return t_ns * 1e-9
