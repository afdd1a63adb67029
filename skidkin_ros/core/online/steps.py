"""The wheel steps an online calibrator keeps: appended per sample, read per reference pose.

Per wheel sample the learner appends the step's end stamp to one list and one tuple to another:
(start stamp, wheel speeds, model v_x and yaw rate, chain id, and the running sums of the
model's travel |v_x| dt and rotation omega dt up to the step's end). Nothing else is computed
per sample. When a reference pose is judged (10 Hz, not 1 kHz) the wheel travel and rotation
since the last one are two differences of those running sums, corrected for the parts of the
end steps outside the span (no loop over the steps); a learning segment converts only its own
steps' speeds to arrays, once per segment.

A chain id tells contiguous steps from steps after a gap: a span whose first and last steps
belong to different chains is not covered.
"""

from __future__ import annotations

import bisect

import numpy as np

__all__ = ['WheelSteps', 'T0', 'LEFT', 'RIGHT', 'V_X', 'YAW_RATE', 'CHAIN', 'TRAVEL', 'TURN']

# The fields of a step's tuple.
T0, LEFT, RIGHT, V_X, YAW_RATE, CHAIN, TRAVEL, TURN = range(8)


class WheelSteps:
    """Wheel steps (t0, t1] of one learner (module docstring)."""

    def __init__(self) -> None:
        self.t1: list[int] = []      # end stamps (ns), increasing: what spans are found by
        # per step: (t0, left, right, model v_x, model yaw rate, chain id, travel, turn)
        self.rows: list[tuple[int, float, float, float, float, int, float, float]] = []

    def __len__(self) -> int:
        return len(self.t1)

    def first_start(self) -> int | None:
        """Return the start stamp of the oldest step kept (None: none)."""
        return self.rows[0][T0] if self.rows else None

    def span(self, t_a: int, t_b: int) -> tuple[int, int] | None:
        """Return the steps (i0, i1) that cover (t_a, t_b] in one chain, else None."""
        t1 = self.t1
        i0 = bisect.bisect_right(t1, t_a)
        i1 = bisect.bisect_left(t1, t_b)
        rows = self.rows
        if (i1 >= len(t1) or i0 > i1 or rows[i0][T0] > t_a
                or rows[i0][CHAIN] != rows[i1][CHAIN]):
            return None
        return i0, i1

    def motion(self, t_a: int, t_b: int) -> tuple[float, float] | None:
        """Return the model's travel (m) and rotation (rad) over (t_a, t_b]; None: not covered.

        The running sums' difference from the end of the first step to the end of the last,
        plus the first step's part inside the span, less the last step's part after it.
        """
        span = self.span(t_a, t_b)
        if span is None:
            return None
        i0, i1 = span
        first, last = self.rows[i0], self.rows[i1]
        head_s = (self.t1[i0] - max(first[T0], t_a)) * 1e-9
        end = self.t1[i1]
        tail_s = (end - min(end, t_b)) * 1e-9
        dist = (last[TRAVEL] - first[TRAVEL] + abs(first[V_X]) * head_s
                - abs(last[V_X]) * tail_s)
        rot = last[TURN] - first[TURN] + first[YAW_RATE] * head_s - last[YAW_RATE] * tail_s
        return max(dist, 0.0), rot

    def speeds(self, t_a: int, t_b: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Return the left and right speeds and durations (s) of the steps over (t_a, t_b].

        The end steps are cut at t_a and t_b (as the calibrator's segments cut them); None when
        the steps do not cover the span in one chain.
        """
        span = self.span(t_a, t_b)
        if span is None:
            return None
        i0, i1 = span
        chunk = self.rows[i0:i1 + 1]
        count = len(chunk)
        stamps = np.array(self.t1[i0:i1 + 1], dtype=np.int64)
        starts = np.fromiter((row[T0] for row in chunk), np.int64, count)
        left = np.fromiter((row[LEFT] for row in chunk), float, count)
        right = np.fromiter((row[RIGHT] for row in chunk), float, count)
        dt_s = (np.minimum(stamps, t_b) - np.maximum(starts, t_a)) * 1e-9
        return left, right, dt_s

    def drop(self, count: int) -> None:
        """Drop the oldest ``count`` steps."""
        del self.t1[:count]
        del self.rows[:count]
