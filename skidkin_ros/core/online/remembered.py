"""Online calibration: the grounds remembered across a restart (written, then taken up).

``~/save_calibration`` (:mod:`skidkin_ros.core.online.save`) writes the active ground as the
model's parameters and every other remembered ground as ``online.grounds.*``
(:mod:`skidkin_ros.core.odometry.saved_grounds` holds their schema and check). On the next
start, :func:`remember` gives the learner those grounds besides the one it starts on, each as
the active one is seeded from ``models.<m>.*`` and its ``parameter_covariance``: its values
are its anchor, its information (and prior) the inverse of its saved covariance. Unlike the
active ground's, whose covariance may come from the offline calibrator and is held at least as
broad as the prior (``online.prior_sigma``, a floor of its information), a remembered
ground's covariance is online calibration's own, the prior already in it: added again, every
save and restart would shrink it (by 1-2 % a cycle on the study's drives) with no new data.
Nothing else is carried: no window of segments (the new drive's segments learn it further),
no history of switches (the
holding blend and the dwell model of ``holding.py`` and ``dwell.py`` wait for the new drive to
show that its grounds alternate: yesterday's alternation says nothing about today's drive).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from skidkin_ros.core.odometry.saved_grounds import SavedGrounds
from skidkin_ros.core.online.calibrator import OnlineCalibrator
from skidkin_ros.core.online.grounds import Ground
from skidkin_ros.errors import ConfigError

__all__ = ['remember', 'remembered_values']


def remember(learner: OnlineCalibrator, saved: SavedGrounds) -> None:
    """Add the file's remembered grounds to a learner that has not learned yet."""
    names = tuple(learner.model.param_names)
    if tuple(saved.names) != names:
        raise ConfigError(
            f'the remembered grounds (online.grounds.*) hold the parameters {list(saved.names)}, '
            f'the learner learns {list(names)}; save the calibration again with this version, '
            'or delete the online.grounds.* entries')
    scale = np.outer(learner.scale, learner.scale)
    for k, cov, metres in zip(saved.values, saved.covariance, saved.learned_m):
        info = np.linalg.inv(cov / scale)
        info = 0.5 * (info + info.T)
        ground = Ground(learner._next_ident, np.asarray(k, dtype=float).copy(), info)
        ground.learned_m = float(metres)
        ground.remembered = True
        learner._next_ident += 1
        learner.grounds.append(ground)
    learner.counters['online_grounds_remembered'] += len(saved)


def remembered_values(config_model: str, learner: OnlineCalibrator) -> dict[str, Any]:
    """Return the ``online.grounds.*`` entries of the learner's grounds besides the active one."""
    others = [g for g in learner.grounds if g is not learner.active]
    if not others:
        return {'online.grounds.model': '', 'online.grounds.parameter_names': '',
                'online.grounds.parameters': [], 'online.grounds.covariance': [],
                'online.grounds.learned_m': []}
    scale = np.outer(learner.scale, learner.scale)
    covariances = []
    for ground in others:
        cov = np.linalg.inv(ground.info) * scale
        covariances.append(0.5 * (cov + cov.T))
    return {'online.grounds.model': config_model,
            'online.grounds.parameter_names': ', '.join(learner.model.param_names),
            'online.grounds.parameters': [float(v) for g in others for v in g.k],
            'online.grounds.covariance': [float(v) for c in covariances for v in c.ravel()],
            'online.grounds.learned_m': [float(g.learned_m) for g in others]}
