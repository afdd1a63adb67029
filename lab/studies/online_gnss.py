"""Online calibration against a GNSS reference without a heading, beside the other odometries.

The drives of :mod:`lab.studies.online` (long stretches: the calibration ground, then from half
the drive a ground 25 % slower in translation and 15 % in yaw; effect-free: the calibration
ground throughout), 240 s each. The reference is a GNSS antenna: its position (the truth at
``MOUNT`` on the robot) with 2 cm of white noise, at 1, 5 or 10 Hz, an identity orientation and
the rotations' variance 99999 (gps_common's utm_odometry, navsat converters). Side by side on the
same wheel samples, scored by eps_t and eps_th over 2 m of true path
(:func:`lab.studies.online._scores`):

* ``fixed``: the calibrated file (:func:`lab.studies.online.calibrated_file`);
* ``true``: the simulator's parameters of the ground under the robot (the floor);
* ``full``: online calibration from a full-pose reference (10 Hz, 1 cm / 3 mrad: a lidar
  odometry), the study's own;
* ``heading taken``: the GNSS poses with ``online.reference_heading: measured`` (what the
  learner did before the heading rule: the constant heading taken for a measured one);
* ``auto``: the default (the heading is found unmeasured, nothing is learned: the file's);
* ``positions N Hz``: ``online.position_only`` at N Hz (learning from the positions alone).

Run: ``python -m lab.bench.online_gnss`` (a few minutes).
"""

from __future__ import annotations

import math
import time

from lab.studies.online import _effects, _reference, _scores, _true_poses
import numpy as np
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.core.online import online_odometer
from skidkin_ros.sim.simulate import SimConfig, simulate

__all__ = ['run_drive', 'COLUMNS', 'MOUNT', 'GNSS_SIGMA_M']

MOUNT = (0.3, 0.1)    # the antenna on the robot (m), as on many field robots
GNSS_SIGMA_M = 0.02
COLUMNS = ('fixed', 'true', 'full', 'heading taken', 'auto', 'positions 1 Hz',
           'positions 5 Hz', 'positions 10 Hz')


def gnss(sim, rate_hz: float, seed: int, mount=MOUNT) -> PoseTrack:
    """Return the antenna's positions with GNSS_SIGMA_M of noise, no heading."""
    t = np.arange(sim.start_ns, sim.end_ns, int(round(1e9 / rate_hz)))
    truth = sim.truth_at(t)
    rng = np.random.default_rng(1000 + seed)
    n = len(t)
    c, s = np.cos(truth.yaw), np.sin(truth.yaw)
    x = truth.x + c * mount[0] - s * mount[1] + rng.normal(0, GNSS_SIGMA_M, n)
    y = truth.y + s * mount[0] + c * mount[1] + rng.normal(0, GNSS_SIGMA_M, n)
    return PoseTrack(t, x, y, np.zeros(n), yaw_variance=np.full(n, 99999.0))


def run_drive(case: str, seed: int, fixed: OdometryConfig, duration_s: float = 240.0) -> dict:
    """Return {column: (eps_t, eps_th, process CPU s)} and the path length of one drive."""
    sim = simulate(SimConfig(duration_s=duration_s, seed=seed, effects=_effects(case)))
    online = {**fixed.values, 'online.enabled': True}
    mount = {'online.mount_x': MOUNT[0], 'online.mount_y': MOUNT[1]}
    out = {}

    def score(name, poses, cpu=math.nan):
        e_t, e_th = _scores(sim, poses)
        out[name] = (float(e_t.mean()), float(e_th.mean()), cpu)

    score('fixed', Odometer.from_config(fixed).predict(sim.wheels).poses)
    score('true', _true_poses(sim, fixed['interval']))
    runs = [('full', online, _reference(sim, np.random.default_rng(seed))),
            ('heading taken', {**online, **mount, 'online.reference_heading': 'measured'},
             gnss(sim, 5.0, seed)),
            ('auto', {**online, **mount}, gnss(sim, 5.0, seed))]
    runs += [(f'positions {rate} Hz', {**online, **mount, 'online.position_only': True},
              gnss(sim, float(rate), seed)) for rate in (1, 5, 10)]
    for name, flat, reference in runs:
        odometer = online_odometer(OdometryConfig.from_flat(flat))
        tic = time.process_time()
        poses = odometer.predict(sim.wheels, reference=reference).poses
        score(name, poses, time.process_time() - tic)
    out['path_m'] = float(sim.truth.path_length()[-1])
    return out
