"""Segment end poses predicted by any twist source, stateful or not, over whole drives.

The diagnosis fits augmented models (a lag, a time offset) whose state evolves along a drive as
it does in the node; a segment cannot then be integrated on its own from zero state.
:class:`SegmentPredictor` runs the source over every drive once and composes each segment from
the drive's cumulative poses. With a plain base model and no offset it computes what
:func:`skidkin_ros.core.calibration.fitting.predict_end_poses` does, to rounding: its rollouts
take their sines and cosines from the tangent of the half angle
(:func:`~skidkin_ros.core.odometry.se2.sin_cos`, a few 1e-16 from numpy's sin and cos and
several times cheaper; the fits evaluate them thousands of times).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from skidkin_ros.core.calibration.segments import segment_frame_error, SegmentSet
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.kinematics.augmented_tangents import base_tangents, interval_tangents
from skidkin_ros.core.odometry.integrator import (body_increment, compose, is_stateful,
                                                  rollout_columns)
from skidkin_ros.core.odometry.interval import check_interval, DEFAULT_INTERVAL, held_wheels
from skidkin_ros.core.odometry.se2_tangent import (body_increment_tangent, compose_tangent,
                                                   window_tangents)

__all__ = ['SegmentPredictor']

# The rollouts' trigonometry (:func:`~skidkin_ros.core.odometry.se2.sin_cos`): the fits need
# the end poses to rounding, not the node's bits.
EXACT_TRIG = False
# How far (ns) outside its drive's stamps a window edge is searched for as it is (farther: at
# this distance, which finds the same place); an hour.
_KEY_MARGIN_NS = 3_600_000_000_000


def _pad_drives(drives: Sequence[Drive], interval: str
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pad the drives' stamps and held speeds (:func:`held_wheels`) to (D, L) arrays."""
    width = max(max((len(d.wheels) for d in drives), default=1), 1)
    count = len(drives)
    t = np.zeros((count, width), dtype=np.int64)
    wl = np.zeros((count, width))
    wr = np.zeros((count, width))
    sizes = np.zeros(count, dtype=int)
    for i, drive in enumerate(drives):
        wheels = held_wheels(drive.wheels, interval)
        n = len(wheels)
        sizes[i] = n
        if n == 0:
            continue
        t[i, :n] = wheels.t_ns
        t[i, n:] = wheels.t_ns[-1]
        wl[i, :n] = wheels.omega_l
        wr[i, :n] = wheels.omega_r
        wl[i, n:] = wheels.omega_l[-1]
        wr[i, n:] = wheels.omega_r[-1]
    return t, wl, wr, sizes


class SegmentPredictor:
    """Predict segment end poses with any (stateful) source, over whole drives.

    The source runs over every drive (its state evolves along the drive as in the node); each
    segment then integrates the mean twists of the wheel speeds held (under the sample-interval
    convention ``interval``) over its window
    [t_a - offset, t_b - offset] from its ground-truth start pose. With a plain base model and no
    offset this is exactly what :func:`skidkin_ros.core.calibration.fitting.predict_end_poses`
    computes.
    """

    def __init__(self, drives: Sequence[Drive], segments: SegmentSet,
                 max_dt_s: float = 0.5, interval: str = DEFAULT_INTERVAL) -> None:
        self.drives = list(drives)
        self.segments = segments
        self.interval = check_interval(interval)
        self.t_ns, self.omega_l, self.omega_r, self.sizes = _pad_drives(self.drives, interval)
        dt = np.zeros(self.t_ns.shape)
        dt[:, :-1] = np.diff(self.t_ns, axis=1) * 1e-9
        self.restart = np.zeros(self.t_ns.shape, dtype=bool)
        self.restart[:, 1:] = dt[:, :-1] > max_dt_s
        dt[dt > max_dt_s] = 0.0
        self.dt_s = dt
        # fixed from here on (read-only: the lag's row plan is kept for them)
        for array in (self.dt_s, self.restart, self.t_ns, self.omega_l, self.omega_r):
            array.setflags(write=False)
        self.step_s = np.diff(self.t_ns, axis=1) * 1e-9  # between stamps, gaps included
        self._plans: dict[int, dict[str, np.ndarray]] = {}
        self._keys: tuple[np.ndarray, np.ndarray, int] | None = None

    def __len__(self) -> int:
        return len(self.segments)

    def plan(self, offset_ns: int) -> dict[str, np.ndarray]:
        """Return how each segment's window [t_a - offset, t_b - offset] meets the samples.

        Flat sample indices (into the padded (D, L) arrays) and durations, one per segment:
        ``first``/``first_s``: the sample held from the window start to the first stamp inside
        it (to the window end when none is inside); ``a``/``b``: the first and last stamps inside
        (equal when none is: no whole interval); ``last_s``: how long sample ``b`` is held from
        its stamp to the window end (0 s when no stamp is inside).
        """
        cached = self._plans.get(offset_ns)
        if cached is not None:
            return cached
        seg = self.segments
        keys, starts, span = self._stamp_keys()
        top = self.sizes[seg.drive] - 1
        row = seg.drive * self.t_ns.shape[1]
        s_a = seg.t_a_ns.astype(np.int64) - offset_ns
        s_b = seg.t_b_ns.astype(np.int64) - offset_ns
        # every drive's stamps in one sorted array (see _stamp_keys): one search for all
        lo = np.searchsorted(keys, self._query_keys(seg.drive, s_a, span),
                             side='right') - starts[seg.drive]
        hi = np.maximum(np.searchsorted(keys, self._query_keys(seg.drive, s_b, span),
                                        side='left') - starts[seg.drive], lo)
        inner = hi > lo
        a = np.clip(lo, 0, top)
        b = np.where(inner, hi - 1, a)
        stamps = self.t_ns.ravel()
        plan = {'first': np.clip(lo - 1, 0, top) + row, 'a': a + row, 'b': b + row,
                'first_s': np.where(inner, stamps[a + row] - s_a, s_b - s_a) * 1e-9,
                'last_s': np.where(inner, s_b - stamps[b + row], 0) * 1e-9}
        if len(self._plans) > 64:
            self._plans.clear()
        self._plans[offset_ns] = plan
        return plan

    def _stamp_keys(self) -> tuple[np.ndarray, np.ndarray, int]:
        """Return every drive's stamps as one increasing array, where each drive starts, the span.

        Drive d's stamp t becomes d * span + margin + (t - its first stamp): the drives'
        blocks are disjoint and in order, so one binary search finds a time's place in its own
        drive's stamps (:meth:`_query_keys`), as a search in that drive alone does.
        """
        if self._keys is None:
            count = len(self.sizes)
            first = self.t_ns[:, 0]
            local = self.t_ns - first[:, None]
            extent = int(local.max(initial=0))
            span = extent + 2 * _KEY_MARGIN_NS + 1
            rows = [d * span + _KEY_MARGIN_NS + local[d, :self.sizes[d]] for d in range(count)]
            keys = np.concatenate(rows) if rows else np.zeros(0, dtype=np.int64)
            starts = np.concatenate([[0], np.cumsum(self.sizes)[:-1]]).astype(np.int64)
            self._keys = (keys, starts, span)
        keys, starts, span = self._keys
        return keys, starts, span

    def _query_keys(self, drive: np.ndarray, t_ns: np.ndarray, span: int) -> np.ndarray:
        """Return the keys of times in their drives (:meth:`_stamp_keys`).

        A time more than the margin before a drive's first stamp or after its last is moved to
        the margin: it stays before (after) every stamp of its drive, so its place is the same.
        """
        local = t_ns - self.t_ns[drive, 0]
        extent = span - 2 * _KEY_MARGIN_NS - 1
        return drive * span + _KEY_MARGIN_NS + np.clip(local, -_KEY_MARGIN_NS,
                                                       extent + _KEY_MARGIN_NS)

    def cumulative_poses(self, mean: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the dead-reckoned pose at every stamp of every drive, flat (D * L,) each.

        Each drive starts at the origin and integrates every sample interval with its mean
        twist, for the time between the stamps (as a segment does, gaps included).
        """
        count, width = self.t_ns.shape
        if width < 2:
            zeros = np.zeros(count * width)
            return zeros, zeros.copy(), zeros.copy()
        rows = mean.reshape(count, width, 3)
        x, y, yaw = rollout_columns(np.ascontiguousarray(rows[:, :-1, 0]),
                                    np.ascontiguousarray(rows[:, :-1, 1]),
                                    np.ascontiguousarray(rows[:, :-1, 2]), self.step_s,
                                    np.zeros((count, 3)), EXACT_TRIG)
        return x.ravel(), y.ravel(), yaw.ravel()

    def mean_twists(self, source: Any) -> np.ndarray:
        """Return the mean twist over every sample interval of every drive, flat (D * L, 3)."""
        if is_stateful(source):
            _, mean = source.intervals(self.t_ns, self.omega_l, self.omega_r, self.dt_s,
                                       self.restart)
        else:
            mean = np.asarray(source.twist(self.omega_l, self.omega_r), dtype=float)
        return mean.reshape(-1, 3)

    def predict_ends(self, source: Any, keep: np.ndarray | None = None) -> np.ndarray:
        """Return the predicted end pose (S, 3) of every segment (or of ``keep`` indices).

        The end pose is the start pose composed with three moves: the partial interval up to
        the first stamp inside the window, the dead-reckoned motion between the first and last
        stamps inside it (from the drive's cumulative poses: one rollout per drive, shared by
        every segment), and the partial interval to the window end. The same steps as
        integrating each window on its own, in O(samples + segments).
        """
        plan = self.plan(int(getattr(source, 'output_offset_ns', 0)))
        start = self.segments.start
        if keep is not None:
            plan = {key: value[keep] for key, value in plan.items()}
            start = start[keep]
        mean = self.mean_twists(source)
        cx, cy, cyaw = self.cumulative_poses(mean)
        a, b = plan['a'], plan['b']
        dx, dy = cx[b] - cx[a], cy[b] - cy[a]
        cos_a, sin_a = np.cos(cyaw[a]), np.sin(cyaw[a])
        moves = (body_increment(*mean[plan['first']].T, plan['first_s'], EXACT_TRIG),
                 (cos_a * dx + sin_a * dy, cos_a * dy - sin_a * dx, cyaw[b] - cyaw[a]),
                 body_increment(*mean[b].T, plan['last_s'], EXACT_TRIG))
        x, y, yaw = start[:, 0], start[:, 1], start[:, 2]
        for move in moves:
            x, y, yaw = compose(x, y, yaw, *move, EXACT_TRIG)
        return np.stack([x, y, yaw], axis=-1)

    def errors(self, source: Any, keep: np.ndarray | None = None) -> np.ndarray:
        """Return the end-pose error of every segment in its start frame (true - predicted)."""
        start, end = self.segments.start, self.segments.end
        if keep is not None:
            start, end = start[keep], end[keep]
        with np.errstate(all='ignore'):
            predicted = self.predict_ends(source, keep)
        return segment_frame_error(start, end, predicted)

    def errors_jacobian(self, source: Any, free: Sequence[tuple[int, int]],
                        offset: int | None = None, keep: np.ndarray | None = None
                        ) -> np.ndarray:
        """Return the exact derivatives (S, 3, P) of :meth:`errors` (0 where not finite).

        ``free``: the P parameters as (-1 for the base model or an extension's index, parameter
        index); ``offset``: the column of a free time offset, if any (it moves each window
        [t_a - offset, t_b - offset]: the end pose gains the twist held at the window end and
        loses the one at its start). Forward mode through the mean twists
        (:func:`~skidkin_ros.core.kinematics.augmented_tangents.interval_tangents`), the
        drives' cumulative poses and the three moves of :meth:`predict_ends`. The error is
        true - start * T for the predicted move T, and in the start frame its derivative is
        -dT.
        """
        count, width = self.t_ns.shape
        plan = self.plan(int(getattr(source, 'output_offset_ns', 0)))
        if keep is not None:
            plan = {key: value[keep] for key, value in plan.items()}
        columns = len(free)
        with np.errstate(all='ignore'):
            if is_stateful(source):
                mean, d_mean = interval_tangents(source, self.t_ns, self.omega_l, self.omega_r,
                                                 self.dt_s, self.restart, free)
            else:
                mean = np.asarray(source.twist(self.omega_l, self.omega_r), dtype=float)
                d_mean = base_tangents(source, self.omega_l, self.omega_r, free)
            a, b, first = plan['a'], plan['b'], plan['first']
            poses, sums = window_tangents(
                *(np.ascontiguousarray(mean[..., m]) for m in range(3)),
                np.concatenate([self.step_s, np.zeros((count, 1))], axis=1), *d_mean, a, b,
                EXACT_TRIG)
            cx, cy, cyaw = poses
            turn, mean = sums[2], mean.reshape(-1, 3)
            d_mean = [d.reshape(columns, count * width) for d in d_mean]
            dx, dy = cx[b] - cx[a], cy[b] - cy[a]
            cos_a, sin_a = np.cos(cyaw[a]), np.sin(cyaw[a])
            world_x = sums[0] - cy[b] * turn
            world_y = sums[1] + cx[b] * turn
            mid = (cos_a * dx + sin_a * dy, cos_a * dy - sin_a * dx, cyaw[b] - cyaw[a])
            d_mid = (cos_a * world_x + sin_a * world_y, cos_a * world_y - sin_a * world_x, turn)
            moves = [(body_increment(*mean[first].T, plan['first_s']),
                      body_increment_tangent(*mean[first].T, plan['first_s'],
                                             *(d[:, first] for d in d_mean))),
                     (mid, d_mid),
                     (body_increment(*mean[b].T, plan['last_s']),
                      body_increment_tangent(*mean[b].T, plan['last_s'],
                                             *(d[:, b] for d in d_mean)))]
            size = len(plan['a'])
            pose = (np.zeros(size), np.zeros(size), np.zeros(size))
            d_pose = tuple(np.zeros((columns, size)) for _ in range(3))
            for move, d_move in moves:
                d_pose = compose_tangent(pose[2], move[0], move[1], *d_pose, *d_move)
                pose = compose(*pose, *move)
            if offset is not None:
                self._offset_slope(mean, plan, pose, d_pose, offset)
        jac = -np.stack(d_pose).transpose(2, 0, 1)  # (3, P, S) -> (S, 3, P)
        finite = np.isfinite(np.stack(pose, axis=1)).all(axis=1)
        jac[~(finite[:, None, None] & np.isfinite(jac))] = 0.0
        return jac

    def _offset_slope(self, mean: np.ndarray, plan: dict[str, np.ndarray], pose: tuple,
                      d_pose: tuple, column: int) -> None:
        """Add d T / d offset to ``d_pose`` (in place): the window moves back by the offset.

        The move T over [s_a, s_b] changes by T * twist(s_b) per second of s_b and by
        -twist(s_a) * T per second of s_a; both edges move by -1 s per second of offset.
        """
        inner = plan['last_s'] > 0.0
        end = mean[np.where(inner, plan['b'], plan['first'])]
        start = mean[plan['first']]
        x, y, yaw = pose
        cos_t, sin_t = np.cos(yaw), np.sin(yaw)
        # d T / d s_b: the end twist, turned into the start frame
        end_x = cos_t * end[:, 0] - sin_t * end[:, 1]
        end_y = sin_t * end[:, 0] + cos_t * end[:, 1]
        # d T / d s_a: minus the start twist acting on the whole move
        start_x = -(start[:, 0] - start[:, 2] * y)
        start_y = -(start[:, 1] + start[:, 2] * x)
        d_pose[0][column] += -(end_x + start_x)
        d_pose[1][column] += -(end_y + start_y)
        d_pose[2][column] += -(end[:, 2] - start[:, 2])
