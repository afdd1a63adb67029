"""Hold-out splits: which drives train and which evaluate, when no evaluation drive is given.

The split is deterministic (no random draw), so the same input gives the same calibration (C20).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Sequence

import numpy as np

from skidkin_ros.core.drive import Drive, ImuSamples, PoseTrack, WheelSamples
from skidkin_ros.core.timeunits import s_to_ns
from skidkin_ros.errors import DataError, ParameterError

__all__ = ['HOLDOUT_MODES', 'split_holdout', 'resolve_holdout']

HOLDOUT_MODES = ('auto', 'drive', 'time')


def _time_slice(drive: Drive, t0_ns: int, t1_ns: int, suffix: str) -> Drive:
    wheels = drive.wheels.between(t0_ns, t1_ns)
    truth = drive.truth
    if truth is not None:
        keep = (truth.t_ns >= t0_ns) & (truth.t_ns <= t1_ns)
        truth = PoseTrack(truth.t_ns[keep], truth.x[keep], truth.y[keep], truth.yaw[keep],
                          truth.valid[keep])
    imu = drive.imu
    if imu is not None:
        keep = (imu.t_ns >= t0_ns) & (imu.t_ns <= t1_ns)
        imu = ImuSamples(imu.t_ns[keep], np.asarray(imu.yaw_rate)[keep])
    return replace(drive, name=f'{drive.name}{suffix}', wheels=WheelSamples(
        wheels.t_ns, wheels.omega_l, wheels.omega_r), truth=truth, imu=imu)


def split_holdout(drives: Sequence[Drive], every: int = 3, mode: str = 'auto',
                  block_s: float = 60.0, key: str | None = None
                  ) -> tuple[list[Drive], list[Drive]]:
    """Split drives into (train, evaluate) deterministically, when no evaluation drive is given.

    - ``key`` (e.g. 'calib_step'): a drive goes to evaluation when ``int(meta[key]) % every ==
      every - 1`` (every=2: odd values evaluate, even values train; the Husky table split);
    - mode 'drive': every ``every``-th drive (the last of each group) evaluates;
    - mode 'time': each drive is cut into blocks of ``block_s`` seconds and every ``every``-th
      block evaluates (a block boundary loses at most one segment on each side);
    - mode 'auto': 'drive' when there are at least ``2 * every`` drives, else 'time'.
    """
    if every < 2:
        raise ParameterError(f'every must be >= 2 (one in every blocks evaluates), got {every}')
    if mode not in HOLDOUT_MODES:
        raise ParameterError(f'hold-out mode must be one of {HOLDOUT_MODES}, got {mode!r}')
    if not drives:
        raise DataError('no drive to split')
    if key is not None:
        missing = [d.name for d in drives if key not in d.meta]
        if missing:
            raise DataError(f'drive(s) {missing[:3]} have no {key!r} in their metadata; '
                            'split by drive or time instead')
        train = [d for d in drives if int(d.meta[key]) % every != every - 1]
        evaluate = [d for d in drives if int(d.meta[key]) % every == every - 1]
        return train, evaluate
    if mode == 'auto':
        mode = 'drive' if len(drives) >= 2 * every else 'time'
    if mode == 'drive':
        return ([d for i, d in enumerate(drives) if i % every != every - 1],
                [d for i, d in enumerate(drives) if i % every == every - 1])
    if not block_s > 0:
        raise ParameterError(f'block_s must be > 0 s, got {block_s!r}')
    train, evaluate = [], []
    block_ns = s_to_ns(block_s)
    for drive in drives:
        if len(drive.wheels) == 0:
            continue
        t0 = int(drive.wheels.t_ns[0])
        t_end = int(drive.wheels.t_ns[-1])
        # A drive shorter than 2 * every blocks still gives two evaluation blocks.
        step_ns = max(1, min(block_ns, (t_end - t0) // (2 * every)))
        for index, start in enumerate(range(t0, t_end + 1, step_ns)):
            part = _time_slice(drive, start, min(start + step_ns - 1, t_end), f'@{index}')
            (evaluate if index % every == every - 1 else train).append(part)
    return train, evaluate


def resolve_holdout(train: Sequence[Drive], evaluate: Sequence[Drive] | None, every: int,
                    mode: str, block_s: float, key: str | None
                    ) -> tuple[list[Drive], list[Drive], str]:
    """Return (train, evaluate, how): the given split, or a deterministic hold-out of train."""
    if evaluate is not None:
        return list(train), list(evaluate), 'given'
    train, evaluate = split_holdout(train, every, mode, block_s, key)
    return train, evaluate, f'held out 1 in {every} ({key or mode})'
