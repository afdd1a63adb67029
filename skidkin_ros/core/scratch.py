"""Work arrays kept between calls, for the fits' exact Jacobians, and memory kept mapped.

The tangents of a rollout are P times the size of the twist (one row per fitted parameter), and
a fresh array that large costs more to map than the arithmetic done in it: the Jacobian of a
fit is computed hundreds of times with the same shapes, so its work arrays are kept. One process
at a time uses them (forked workers get their own copies).

:func:`kept_heap` does the same for every other array of a diagnosis: glibc's malloc gives
blocks above 128 KiB (a drive's twist component) fresh pages from the kernel and returns them at
free, so each of the fits' thousands of evaluations paid a page fault per 4 KiB of every
temporary (a tenth of a diagnosis's CPU time, most of it in the kernel). Inside the block freed
memory stays with the process for the next array; at its end the heap is trimmed again.
"""

from __future__ import annotations

from contextlib import contextmanager
import ctypes
import ctypes.util
from typing import Iterator

import numpy as np

__all__ = ['scratch', 'kept_heap']

# glibc's mallopt parameters and their defaults (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
_DEFAULTS = {_M_TRIM_THRESHOLD: 128 * 1024, _M_TOP_PAD: 128 * 1024,
             _M_MMAP_THRESHOLD: 128 * 1024}
_KEPT = {_M_TRIM_THRESHOLD: 1 << 30, _M_TOP_PAD: 64 << 20, _M_MMAP_THRESHOLD: 256 << 20}

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


def _libc():
    """Return glibc with mallopt and malloc_trim, or None (another C library: nothing to do)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6')
        libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
        libc.malloc_trim.argtypes = [ctypes.c_size_t]
        return libc
    except (OSError, AttributeError):
        return None


@contextmanager
def kept_heap() -> Iterator[None]:
    """Keep freed memory mapped in this process for the block (module docstring).

    Arrays up to 256 MiB come from the heap, which is not trimmed below 1 GiB of free space;
    after the block the defaults are set again and the free memory returned to the system.
    Outside glibc this does nothing. The arithmetic is untouched.
    """
    libc = _libc()
    if libc is None:
        yield
        return
    for option, value in _KEPT.items():
        libc.mallopt(option, value)
    try:
        yield
    finally:
        for option, value in _DEFAULTS.items():
            libc.mallopt(option, value)
        libc.malloc_trim(0)
