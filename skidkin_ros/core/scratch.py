"""Work arrays kept between calls, for the fits' exact Jacobians.

The tangents of a rollout are P times the size of the twist (one row per fitted parameter), and
a fresh array that large costs more to map than the arithmetic done in it: the Jacobian of a
fit is computed hundreds of times with the same shapes, so its work arrays are kept. One process
at a time uses them (forked workers get their own copies).
"""

from __future__ import annotations

import numpy as np

__all__ = ['scratch']

_SCRATCH: dict[tuple, np.ndarray] = {}
_MAX_KEPT = 16


def scratch(name: str, shape: tuple[int, ...]) -> np.ndarray:
    """Return the work array ``name`` of ``shape``: uninitialised, reused by the next call."""
    key = (name, tuple(shape))
    array = _SCRATCH.get(key)
    if array is None:
        if len(_SCRATCH) >= _MAX_KEPT:
            _SCRATCH.clear()
        array = _SCRATCH[key] = np.empty(shape)
    return array
