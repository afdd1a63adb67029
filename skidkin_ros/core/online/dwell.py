"""Online calibration while holding: how long the robot stays on each ground (a dwell model).

The Markov chain of ``holding.py`` forgets how long the robot has been on the ground it was on
when the reference was lost: it gives the last ground the same chance to end in the next metre
whether the robot entered it a metre ago or has been on it longer than any stay seen before.
Where the stays have a typical length, that is wrong both ways. This module replaces the chain
by a semi-Markov one in distance, learned from the reference before the loss:

* each ground's stay lengths (metres of reference path between two recognised switches, the
  stays that ended in the last ``online.memory`` m; a ground with fewer than ``MIN_STAYS`` uses
  the stays of all grounds), as a kernel density (a normal kernel of the larger of
  ``online.switch_window``, the recognition's own resolution, and Silverman's width), mixed
  with ``MEMORYLESS`` of an exponential of the same mean (a stay longer than any seen still
  ends; a few stays are not the whole distribution);
* which ground follows which (the switches counted, plus ``PRIOR`` on every other ground);
* the metres already spent on the last ground when the last pose was accepted.

It is used only where the stay-length laws predict the stays seen, each left out in turn,
better than a memoryless law of the same mean (``lengths_explained``): on stays of no typical
length a few of them read as more regular than they are, and the chain is kept there.

From these the probability of each ground after d more metres follows from the renewal
equations (the first stay's remaining length, then whole stays), on a grid of ``STEP_M`` up to
``REACH_M`` (beyond it: the last column, the chain's long-run shares). Computed once per loss
of the reference (about a millisecond), read by interpolation at every look of the blend.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

__all__ = ['MIN_STAYS', 'MEMORYLESS', 'lengths_explained', 'occupancy', 'weights_at']

# Grid step and reach (m of wheel travel since the last pose) of the occupancy table.
STEP_M = 0.1
REACH_M = 50.0
# Share of the stay-length law given to a memoryless (exponential) law of the same mean.
MEMORYLESS = 0.1
# Completed stays a ground needs for its own length law (fewer: the stays of all grounds).
MIN_STAYS = 2
# Switches added to every transition between two different grounds (a prior).
PRIOR = 0.5
# Kernel widths past the longest stay where a normal kernel's density is 0 in floating point.
KERNEL_REACH = 40.0


def _width(lengths: np.ndarray, width_min: float) -> float:
    """Return the kernel's width: the larger of ``width_min`` and Silverman's."""
    sd = float(lengths.std()) if lengths.size > 1 else 0.0
    return max(width_min, 1.06 * sd * lengths.size ** -0.2)


def _length_law(lengths: Sequence[float], width_min: float, size: int) -> np.ndarray:
    """Return P(stay length in cell m), m = 0..size-1 (cell m: within STEP_M / 2 of m STEP_M)."""
    lengths = np.asarray(lengths, dtype=float)
    width = _width(lengths, width_min)
    x = np.arange(size) * STEP_M
    density = np.exp(-0.5 * ((x[:, None] - lengths[None, :]) / width) ** 2).sum(axis=1)
    density[0] = 0.0
    density /= density.sum()
    mean = max(float(lengths.mean()), STEP_M)
    memoryless = np.exp(-x / mean)
    memoryless[0] = 0.0
    memoryless /= memoryless.sum()
    return (1.0 - MEMORYLESS) * density + MEMORYLESS * memoryless


def _own(stays: Sequence[tuple[int, float]], j: int) -> list[float]:
    """Return ground j's stay lengths, or all grounds' where it has fewer than MIN_STAYS."""
    own = [length for g, length in stays if g == j]
    return own if len(own) >= MIN_STAYS else [length for _, length in stays]


def lengths_explained(stays: Sequence[tuple[int, float]], width_min: float) -> bool:
    """Tell whether the stay-length laws predict each stay, left out, better than memoryless.

    Leave-one-out: each completed stay's log density under its ground's law built from the
    other stays, against an exponential law of their mean length; summed over the stays.
    """
    size = max(int(round(REACH_M / STEP_M)),
               int(math.ceil(max(length for _, length in stays) / STEP_M))) + 2
    gain = 0.0
    for i, (g, length) in enumerate(stays):
        rest = list(stays[:i]) + list(stays[i + 1:])
        if not rest:
            return False
        lengths = _own(rest, g)
        cell = min(int(round(length / STEP_M)), size - 1)
        law = _length_law(lengths, width_min, size)
        mean = max(float(np.mean(lengths)), STEP_M)
        memoryless = np.exp(-np.arange(size) * STEP_M / mean)
        memoryless[0] = 0.0
        memoryless /= memoryless.sum()
        gain += math.log(max(law[cell], 1e-300)) - math.log(max(memoryless[cell], 1e-300))
    return gain > 0.0


def occupancy(stays: Sequence[tuple[int, float]], switches: Sequence[tuple[int, int]],
              count: int, elapsed_m: float, width_min: float) -> np.ndarray | None:
    """Return P (count, n) of each ground on the grid of wheel travel 0, STEP_M, ... REACH_M.

    ``stays``: (ground, length m) of the completed stays; ``switches``: (from, to) of the
    switches seen; ground 0 is the one the robot was on at the loss, for ``elapsed_m`` m.
    None where no stay was completed.
    """
    if not stays:
        return None
    n = int(round(REACH_M / STEP_M)) + 1
    # Beyond KERNEL_REACH widths past the longest stay of the last ground, its kernel density
    # is 0 in floating point and what is left is the exponential, which forgets how long the
    # stay has lasted: a longer time spent there reads the same as that cell.
    own = np.asarray(_own(stays, 0), dtype=float)
    calm = int(math.ceil((float(own.max()) + KERNEL_REACH * _width(own, width_min)) / STEP_M))
    m0 = min(int(round(max(elapsed_m, 0.0) / STEP_M)), calm)
    size = n + m0 + 1
    laws = [_length_law(_own(stays, j), width_min, size) for j in range(count)]
    # the chance to last beyond cell m as the sum of the cells beyond it (1 - cumsum loses it
    # below 1e-16, some 35 mean stays on)
    survive = [np.append(np.cumsum(h[:0:-1])[::-1], 0.0) for h in laws]
    moves = np.full((count, count), PRIOR)
    np.fill_diagonal(moves, 0.0)
    for a, b in switches:
        if a != b:
            moves[a, b] += 1.0
    moves /= moves.sum(axis=1, keepdims=True)
    left = max(float(survive[0][m0]), 1e-300)
    first_exit = laws[0][m0:m0 + n] / left        # the current stay ends in cell m
    first_exit[0] = 0.0
    still = np.clip(survive[0][m0:m0 + n] / left, 0.0, 1.0)
    entries = np.zeros((count, n))
    for m in range(1, n):
        exits = np.array([laws[j][1:m + 1] @ entries[j, m - 1::-1] for j in range(count)])
        exits[0] += first_exit[m]
        entries[:, m] = exits @ moves
    table = np.empty((count, n))
    for j in range(count):
        table[j] = np.convolve(entries[j], np.clip(survive[j][:n], 0.0, 1.0))[:n]
    table[0] += still
    return table / table.sum(axis=0, keepdims=True)


def weights_at(table: np.ndarray, travel_m: float) -> np.ndarray:
    """Return the grounds' probabilities after ``travel_m`` m (linear between grid points)."""
    x = max(travel_m, 0.0) / STEP_M
    i = min(int(math.floor(x)), table.shape[1] - 1)
    if i + 1 >= table.shape[1]:
        return table[:, -1].copy()
    f = x - i
    return (1.0 - f) * table[:, i] + f * table[:, i + 1]
