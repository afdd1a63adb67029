"""Joining chunk registrations at their seams, each seam tested on the chunks' overlap.

One job: steps 4 and 5 of :mod:`skidkin_ros.adapters.lidar_chunks` (anchor, seam test, cut,
failed chunks).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Sequence

import numpy as np

from skidkin_ros.adapters.lidar_gt import Registration
from skidkin_ros.adapters.lidar_plan import ChunkOptions, ChunkOutcome, ChunkTask
from skidkin_ros.core.timeunits import s_to_ns
from skidkin_ros.errors import DataError

__all__ = ['Joined', 'join_chunks']


@dataclass
class Joined:
    """The joined registration, the frames that start behind a cut seam, and what happened.

    ``seams_tested``: seams whose overlap was compared; ``seams_failed``: those of them that
    disagreed (cut), ``failed_chunks`` the indices of the chunks after them; ``seams_untested``:
    seams cut without a test (after a failed chunk, or no frame registered by both chunks).
    ``seams_cut`` is their sum (a cut seam with no frame after it is not counted: there is
    nothing to cut); ``cut_chunks`` the indices of the chunks after all of them.
    """

    registration: Registration
    cut_frames: list[int]
    notes: list[str]
    seams_tested: int = 0
    seams_failed: int = 0
    seams_untested: int = 0
    failed_chunks: tuple[int, ...] = ()
    cut_chunks: tuple[int, ...] = ()

    @property
    def seams_cut(self) -> int:
        return self.seams_failed + self.seams_untested

    def seams_note(self, chunks: int, options: ChunkOptions) -> str:
        """Return the one-line summary of the chunks and their seams."""
        note = (f'lidar registered in {chunks} chunks of {options.chunk_s:g} s '
                f'({options.overlap_s:g} s overlap): {self.seams_tested} seam(s) tested, '
                f'{self.seams_failed} of them cut')
        if self.seams_untested:
            note += (f'; {self.seams_untested} cut untested (after a failed chunk or without a '
                     'frame both chunks registered)')
        return note


def _motion(pose_a: np.ndarray, pose_b: np.ndarray) -> np.ndarray:
    return np.linalg.inv(pose_a) @ pose_b


def _rotation_angle(transform: np.ndarray) -> float:
    return math.acos(max(-1.0, min(1.0, (float(np.trace(transform[:3, :3])) - 1.0) / 2.0)))


def _seam_agrees(previous: Registration, prev_rows: np.ndarray, current: Registration,
                 cur_rows: np.ndarray, window_ns: int, options: ChunkOptions) -> bool:
    """Tell whether both chunks moved alike over the common frames before the anchor."""
    anchor_end = previous.end_ns[prev_rows[-1]]
    use = previous.end_ns[prev_rows] >= anchor_end - window_ns
    a_prev, a_cur = previous.lidar_pose[prev_rows[-1]], current.lidar_pose[cur_rows[-1]]
    for i, j in zip(prev_rows[use], cur_rows[use]):
        m_prev = _motion(previous.lidar_pose[i], a_prev)
        m_cur = _motion(current.lidar_pose[j], a_cur)
        moved = float(np.linalg.norm(m_prev[:3, 3]))
        turned = _rotation_angle(m_prev)
        if (np.linalg.norm(m_prev[:3, 3] - m_cur[:3, 3]) > options.seam_abs_m + 0.1 * moved
                or _rotation_angle(_motion(m_prev, m_cur)) > options.seam_abs_rad
                + 0.1 * turned):
            return False
    return True


def join_chunks(outcomes: Sequence[ChunkOutcome], options: ChunkOptions) -> Joined:
    """Join chunk registrations into one (see the module docstring, steps 4 and 5)."""
    parts: list[Registration] = []
    cut: list[int] = []
    notes: list[str] = []
    tested = failed = untested = 0
    failed_chunks: list[int] = []
    cut_chunks: list[int] = []
    offset = 0
    previous: Registration | None = None  # the previous chunk, poses in the joined frame
    window_ns = s_to_ns(options.overlap_s / 2)
    for outcome in outcomes:
        task, reg = outcome.task, outcome.registration
        if reg is None:
            notes.append(f'lidar chunk {task.index} ({_window_text(task)}) failed: '
                         f'{outcome.error}; its frames have no ground truth, the other chunks '
                         'are kept')
            previous = None
            continue
        notes.extend(outcome.notes)
        receive = reg.receive_ns if reg.receive_ns is not None else reg.end_ns
        own = np.ones(len(reg), dtype=bool) if task.seam_ns is None else receive >= task.seam_ns
        first_own = np.flatnonzero(own & reg.registered)
        poses = reg.lidar_pose
        if parts:
            transform, agrees = (None, False) if previous is None else _anchor(
                previous, reg, window_ns, options)
            anchored = transform is not None
            if anchored:
                tested += 1
                if not agrees:
                    notes.append(f'lidar chunk {task.index}: its overlap with chunk '
                                 f'{task.index - 1} disagrees; the seam is cut')
            else:
                if previous is not None:
                    notes.append(f'lidar chunk {task.index}: no frame registered by both '
                                 'chunks at its seam; the seam is cut')
                transform = _continue_from(parts, reg, first_own)
            poses = np.einsum('ij,njk->nik', transform, poses)
            if not agrees and first_own.size:
                cut.append(offset + int(np.count_nonzero(own[:first_own[0]])))
                cut_chunks.append(task.index)
                if anchored:
                    failed += 1
                    failed_chunks.append(task.index)
                else:
                    untested += 1
        previous = Registration(reg.end_ns, reg.status, reg.pose_t_ns, poses,
                                reg.inlier_fraction, reg.residual_m, reg.degeneracy, receive)
        part = _select(previous, own)
        parts.append(part)
        offset += len(part)
    if not parts:
        raise DataError('every lidar chunk failed; no ground truth: ' + '; '.join(notes))
    return Joined(_concatenate(parts), cut, notes, tested, failed, untested,
                  tuple(failed_chunks), tuple(cut_chunks))


def _continue_from(parts: Sequence[Registration], reg: Registration,
                   first_own: np.ndarray) -> np.ndarray:
    """Return the transform that puts a chunk's first pose on the last joined pose (no anchor)."""
    for part in reversed(parts):
        rows = np.flatnonzero(part.registered)
        if rows.size and first_own.size:
            return part.lidar_pose[rows[-1]] @ np.linalg.inv(reg.lidar_pose[first_own[0]])
    return np.eye(4)


def _window_text(task: ChunkTask) -> str:
    start = 'start' if task.start_ns is None else f'{task.start_ns * 1e-9:.1f} s'
    stop = 'end' if task.stop_ns is None else f'{task.stop_ns * 1e-9:.1f} s'
    return f'bag time {start} to {stop}'


def _anchor(previous: Registration, current: Registration, window_ns: int,
            options: ChunkOptions) -> tuple[np.ndarray | None, bool]:
    """Return (transform onto the previous chunk's frame, seam test passed), None: no anchor."""
    common, prev_idx, cur_idx = np.intersect1d(previous.end_ns[previous.registered],
                                               current.end_ns[current.registered],
                                               return_indices=True)
    if common.size == 0:
        return None, False
    prev_rows = np.flatnonzero(previous.registered)[prev_idx]
    cur_rows = np.flatnonzero(current.registered)[cur_idx]
    transform = (previous.lidar_pose[prev_rows[-1]]
                 @ np.linalg.inv(current.lidar_pose[cur_rows[-1]]))
    return transform, _seam_agrees(previous, prev_rows, current, cur_rows, window_ns, options)


def _select(reg: Registration, keep: np.ndarray) -> Registration:
    return Registration(reg.end_ns[keep], tuple(s for s, k in zip(reg.status, keep) if k),
                        reg.pose_t_ns[keep], reg.lidar_pose[keep], reg.inlier_fraction[keep],
                        reg.residual_m[keep], reg.degeneracy[keep],
                        None if reg.receive_ns is None else reg.receive_ns[keep])


def _concatenate(parts: Sequence[Registration]) -> Registration:
    status: list[str] = []
    for part in parts:
        status.extend(part.status)
    return Registration(
        np.concatenate([p.end_ns for p in parts]), tuple(status),
        np.concatenate([p.pose_t_ns for p in parts]),
        np.concatenate([p.lidar_pose for p in parts]),
        *(np.concatenate([getattr(p, name) for p in parts])
          for name in ('inlier_fraction', 'residual_m', 'degeneracy')),
        receive_ns=np.concatenate([p.receive_ns if p.receive_ns is not None else p.end_ns
                                   for p in parts]))
