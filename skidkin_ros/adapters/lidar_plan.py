"""Chunks of a recording's lidar: how to cut and where to run, the tasks, and their outcomes.

One job: planning the chunks (step 1 of :mod:`skidkin_ros.adapters.lidar_chunks`) and the
types every other step passes around (options, one task, one task's outcome).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Sequence

from skidkin_ros.adapters.lidar_gt import FrameGrid, IcpConfig, Registration
from skidkin_ros.core.timeunits import s_to_ns
from skidkin_ros.errors import ParameterError

__all__ = ['ChunkOptions', 'ChunkOutcome', 'ChunkTask', 'plan_chunks']


@dataclass(frozen=True)
class ChunkOptions:
    """How to cut and where to run: chunk length and overlap (s), processes, Dask scheduler.

    ``jobs``: local processes (1: in this process); ``cluster``: a Dask scheduler address
    (``tcp://host:8786``; the workers need skidkin_ros and the recording at the same path);
    ``seam_abs_m`` / ``seam_abs_rad``: the seam test's tolerances.
    """

    chunk_s: float = 60.0
    overlap_s: float = 4.0
    jobs: int = 1
    cluster: str | None = None
    seam_abs_m: float = 0.25
    seam_abs_rad: float = 0.05

    def __post_init__(self) -> None:
        if not self.chunk_s >= 5.0:
            raise ParameterError(f'chunk length must be >= 5 s, got {self.chunk_s}')
        if not 0.5 <= self.overlap_s <= self.chunk_s / 2:
            raise ParameterError('chunk overlap must be between 0.5 s and half the chunk '
                                 f'length, got {self.overlap_s} s for chunks of {self.chunk_s} s')
        if not isinstance(self.jobs, int) or self.jobs < 1:
            raise ParameterError(f'jobs must be a whole number >= 1, got {self.jobs!r}')
        if self.seam_abs_m <= 0 or self.seam_abs_rad <= 0:
            raise ParameterError('seam tolerances must be > 0')


@dataclass(frozen=True)
class ChunkTask:
    """One chunk: the recording, the lidar topic and the bag-time window to register.

    ``start_ns`` / ``stop_ns``: receive-time window ([start, stop), None: open); ``seam_ns``:
    where the chunk's own part begins (its frames before it are the warm-up; None: chunk 0).
    """

    bag: str
    topic: str
    index: int
    start_ns: int | None
    stop_ns: int | None
    seam_ns: int | None
    config: IcpConfig
    grid: FrameGrid | None = None


@dataclass
class ChunkOutcome:
    """What one chunk gave: its registration, or why it failed; read from the cache or not."""

    task: ChunkTask
    registration: Registration | None = None
    error: str | None = None
    notes: list[str] = field(default_factory=list)
    cached: bool = False


def plan_chunks(bag: str, topic: str, first_receive_ns: int, period_ns: int, n_frames: int,
                first_end_ns: int, config: IcpConfig, options: ChunkOptions,
                seams_ns: Sequence[int] | None = None) -> list[ChunkTask]:
    """Cut the recording's lidar into chunks (see the module docstring, step 1).

    The number of chunks comes from the frame count and period; the last chunk is open-ended,
    so nothing is lost when the estimate is short. ``seams_ns``: where chunks 1, 2, ... begin
    (:func:`skidkin_ros.adapters.lidar_calm.calm_seams`); None: every ``chunk_s`` from the
    first cloud.
    """
    chunk_ns = s_to_ns(options.chunk_s)
    overlap_ns = s_to_ns(options.overlap_s)
    if seams_ns is None:
        span_ns = max(int(n_frames), 1) * max(int(period_ns), 1)
        count = max(1, int(math.ceil(span_ns / chunk_ns - 0.25)))
        seams_ns = [first_receive_ns + k * chunk_ns for k in range(1, count)]
    seams = [None] + [int(s) for s in seams_ns]
    if any(b <= a for a, b in zip(seams[1:], seams[2:])):
        raise ParameterError(f'chunk seams must increase, got {seams[1:]}')
    grid = (FrameGrid.for_frames(first_end_ns, period_ns, config.stride)
            if config.stride > 1 else None)
    tasks = []
    for k, seam in enumerate(seams):
        start = seam - overlap_ns if seam is not None else None
        stop = seams[k + 1] if k + 1 < len(seams) else None
        tasks.append(ChunkTask(str(bag), topic, k, start, stop, seam, config, grid))
    return tasks
