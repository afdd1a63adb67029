"""Runtime changes of ``online.*`` that keep what was learned.

A change of an ``online.*`` parameter at runtime rebuilt the learner from the file's parameters,
even for a gate. The parameters in ``KEEP`` judge or weigh what comes next without making what
was learned, or the buffered wheel steps and reference poses, wrong: the learner takes them in
place (the grounds, their windows, the buffers and the delay in force are kept).

The others still restart learning from the file's parameters: ``enabled``, the frames,
``time_offset`` and ``mount_*`` (the buffered poses were converted with the old ones),
``horizon`` and ``horizon_rad`` (the segment in progress was cut by them), ``prior_sigma`` and
``min_information`` (every ground's prior and update rule), ``window`` and ``max_grounds`` (the
sizes of what is kept).
"""

from __future__ import annotations

from dataclasses import fields

from skidkin_ros.core.odometry.reference import OnlineParams
from skidkin_ros.core.online.calibrator import OnlineCalibrator
from skidkin_ros.core.timeunits import NS_PER_S

__all__ = ['KEEP', 'retune']

KEEP = frozenset(('max_rate', 'max_gap', 'max_jump', 'max_jump_rad', 'stall', 'gyro_sigmas',
                  'cusum_drift', 'cusum_threshold', 'switch_window', 'switch_margin',
                  'sigma_xy', 'sigma_yaw', 'memory', 'adapt_memory', 'adapt_distance',
                  'delay_tolerance', 'delay_learn'))


def retune(learner, old: OnlineParams, new: OnlineParams) -> bool:
    """Give ``learner`` the parameters ``new`` in place; False (untouched) unless only KEEP differ.

    ``old``: the learner's parameters until now.
    """
    changed = {f.name for f in fields(OnlineParams)
               if getattr(old, f.name) != getattr(new, f.name)}
    if not changed or not changed <= KEEP or not isinstance(learner, OnlineCalibrator):
        return False
    learner.params = new
    learner._min_period_ns = NS_PER_S / new.max_rate
    learner._delay.tolerance_s = new.delay_tolerance
    learner._delay.learn = new.delay_learn > 0.5
    return True
