"""Save what online calibration learned as a parameters file the node loads as is."""

from __future__ import annotations

import datetime
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from skidkin_ros.atomic import check_writable
from skidkin_ros.core.odometry.config import OdometryConfig, write_params_file
from skidkin_ros.core.online.calibrator import OnlineCalibrator
from skidkin_ros.core.online.remembered import remembered_values
from skidkin_ros.errors import OutputError

__all__ = ['learned_values', 'save_learned']


def learned_values(config: OdometryConfig, learner: OnlineCalibrator) -> dict[str, Any]:
    """Return the configuration's parameters with the active model's replaced by the learned ones.

    The parameter covariance is the learner's (what the published covariance carries); the
    other grounds it remembers are ``online.grounds.*`` (:mod:`.remembered`).
    """
    values = dict(config.values)
    name = learner.model.name
    cov = learner.covariance
    file_values = getattr(learner.model, 'file_values', None)
    if file_values is not None:  # an augmented model: models.<base>.*, augmented.<ext>.*
        values.update(file_values(learner.k))
        size = len(learner.model.base.params)
        cov = cov[:size, :size]
        name = learner.model.base.name
    else:
        for key, value in learner.values.items():
            values[f'models.{name}.{key}'] = float(value)
    if cov.size:
        values[f'models.{name}.parameter_covariance'] = (0.5 * (cov + cov.T)).ravel().tolist()
    values.update(remembered_values(config.model, learner))   # the other grounds (remembered.py)
    return values


def save_learned(config: OdometryConfig, learner: OnlineCalibrator, path: str | Path,
                 provenance: Mapping[str, Any] | None = None) -> Path:
    """Write the learned parameters atomically (umask honoured); an existing file is refused.

    ``path`` empty: ``skidkin_online_<UTC time>.yaml`` in the working directory. The file is
    checked by the node's own validation before it is written, and its provenance says where
    and when it was learned (the reference, the distance, the ground).
    """
    now = datetime.datetime.now(datetime.timezone.utc)
    # '~' expanded: a ROS parameter reaches the node as typed, no shell expands it
    target = Path(path).expanduser() if str(path) else _default_target(now)
    if target.exists() and not target.is_dir():
        raise OutputError(f'{target} exists and is never overwritten (it may be the file the '
                          'node loaded); set online.save_path to a new file name')
    # a folder, a missing folder, one not writable: said in the node's terms, before writing
    check_writable(target, False, 'online.save_path')
    summary = learner.summary()
    prov = {'source': 'online calibration (skidkin_ros odom_node ~/save_calibration)',
            'date': now.isoformat(timespec='seconds'), 'model': learner.model.name,
            'ground': int(summary['ground']), 'grounds_known': int(summary['grounds']),
            'learned_on_ground_m': float(summary['learned_m']),
            'reference_travel_m': float(summary['travel_m']),
            'segments': int(learner.counters['online_segments']),
            'changes_detected': int(learner.counters['online_change']),
            'started_from_robot': config['robot'],
            'parameter_sigma': [float(v) for v in np.sqrt(np.diag(learner.covariance))]}
    prov.update(provenance or {})
    return write_params_file(target, learned_values(config, learner), prov)


def _default_target(now: datetime.datetime) -> Path:
    """Return skidkin_online_<UTC time>.yaml in the working directory, _2, _3... if taken."""
    stem = now.strftime('skidkin_online_%Y%m%dT%H%M%SZ')
    target, n = Path.cwd() / f'{stem}.yaml', 2
    while target.exists() or target.is_symlink():   # two saves in one second
        target, n = Path.cwd() / f'{stem}_{n}.yaml', n + 1
    return target
