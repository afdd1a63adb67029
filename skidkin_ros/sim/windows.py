"""Windowed drives like the DRIVE protocol's: short windows, many spins, transients.

Why: the DRIVE tables (the Husky one in ``data/husky``, the Warthog one of the same project) are
not long drives but independent windows of 2 s: each ``calib_step`` is one commanded (left,
right) pair drawn uniformly over the input space and held for about 6 s, cut into consecutive
windows. So a third of the windows or more barely translate (spins and slow turns), and the first
window of every step holds the transient from the previous command. A calibration that works on
long drives must also work there.

:func:`simulate_windows` makes such data with the project's simulator, as a recipe:

1. draw ``steps`` command pairs uniformly in [-max, max]^2 rad/s (many spins come by
   themselves: opposite signs);
2. simulate one scripted drive that holds each pair ``hold_s`` (true model and effects from the
   config: by default a Warthog-like robot, r = 0.3 m, b = 1.2 m, asymmetric treads, and
   dynamics no kinematic model has: acceleration slip and a yaw lag);
3. cut it into windows of ``window_s`` (one Drive each, ``meta['calib_step']`` = the step index,
   so ``split_holdout(key='calib_step')`` gives the DRIVE split), the truth with
   ``truth_noise`` (m, rad) of white noise like an ICP ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import logging
from typing import Mapping

import numpy as np

from skidkin_ros.core.drive import Drive, PoseTrack, WheelSamples
from skidkin_ros.core.timeunits import s_to_ns
from skidkin_ros.errors import ParameterError
from skidkin_ros.sim.effects import Effect, make_effect
from skidkin_ros.sim.simulate import SimConfig, simulate

__all__ = ['WindowedConfig', 'WARTHOG_LIKE', 'simulate_windows']

_LOG = logging.getLogger(__name__)


@dataclass(frozen=True)
class WindowedConfig:
    """A DRIVE-like windowed recording (module docstring); lengths in m, times in s."""

    steps: int = 100
    hold_s: float = 6.0
    window_s: float = 2.0
    max_wheel_speed_rad_s: float = 15.0
    seed: int = 0
    wheel_radius: float = 0.3
    track_width: float = 1.2
    true_params: Mapping[str, float] = field(default_factory=lambda: {
        'alpha_l': 0.93, 'alpha_r': 0.86, 'x_v': -0.08, 'y_l': 0.95, 'y_r': -1.1})
    effects: tuple[Effect, ...] = field(default_factory=lambda: (
        make_effect('first_order_lag', 0.4), make_effect('acceleration_slip', 0.25),
        make_effect('ratio_yaw_slip', 0.3), make_effect('speed_slip', 0.05)))
    motor_tau_s: float = 0.25
    encoder_noise_rad_s: float = 0.05
    truth_noise: tuple[float, float] = (0.005, 0.003)

    def __post_init__(self) -> None:
        if self.steps < 2:
            raise ParameterError(f'steps must be >= 2 (train and evaluate), got {self.steps!r}')
        if not 0 < self.window_s <= self.hold_s:
            raise ParameterError(f'window_s must be in (0, hold_s = {self.hold_s:g}] s, got '
                                 f'{self.window_s!r}')


WARTHOG_LIKE = WindowedConfig()


def _commands(config: WindowedConfig) -> np.ndarray:
    rng = np.random.default_rng([config.seed, 7])
    top = config.max_wheel_speed_rad_s
    return rng.uniform(-top, top, size=(config.steps, 2))


def _window(name: str, wheels: WheelSamples, truth: PoseTrack, t0: int, t1: int,
            rng: np.random.Generator, noise: tuple[float, float], step: int) -> Drive:
    keep_w = (wheels.t_ns >= t0) & (wheels.t_ns < t1)
    keep_t = (truth.t_ns >= t0) & (truth.t_ns < t1)
    n = int(keep_t.sum())
    xy_sd, yaw_sd = noise
    track = PoseTrack(truth.t_ns[keep_t], truth.x[keep_t] + rng.normal(0, xy_sd, n),
                      truth.y[keep_t] + rng.normal(0, xy_sd, n),
                      truth.yaw[keep_t] + rng.normal(0, yaw_sd, n))
    return Drive(name, WheelSamples(wheels.t_ns[keep_w], wheels.omega_l[keep_w],
                                    wheels.omega_r[keep_w]), track,
                 meta={'calib_step': step, 'source': 'skidkin_ros.sim.windows'})


def simulate_windows(config: WindowedConfig = WARTHOG_LIKE) -> list[Drive]:
    """Return the windows of one simulated DRIVE-like recording (module docstring)."""
    commands = _commands(config)
    script = tuple((config.hold_s, float(left), float(right)) for left, right in commands)
    rest_s = 1.0
    duration = rest_s + config.hold_s * config.steps
    sim_config = SimConfig(
        duration_s=duration, seed=config.seed, wheel_radius=config.wheel_radius,
        track_width=config.track_width, true_model='edd_asymmetric',
        true_params=dict(config.true_params), effects=tuple(config.effects),
        internal_rate_hz=200.0, motor_tau_s=config.motor_tau_s,
        encoder_noise_rad_s=config.encoder_noise_rad_s, script=script,
        max_wheel_speed_rad_s=max(config.max_wheel_speed_rad_s, 0.1),
        scene_half_size_m=1000.0, arena_radius_m=500.0)
    sim_log = logging.getLogger('skidkin_ros.sim.simulate')
    level = sim_log.level
    sim_log.setLevel(logging.ERROR)  # the scripted drive may leave the scene: no lidar here
    try:
        sim = simulate(sim_config)
    finally:
        sim_log.setLevel(level)
    rng = np.random.default_rng([config.seed, 11])
    per_step = int(round(config.hold_s / config.window_s))
    drives = []
    for step in range(config.steps):
        start = sim.start_ns + s_to_ns(rest_s + step * config.hold_s)
        for j in range(per_step):
            t0 = start + s_to_ns(j * config.window_s)
            t1 = t0 + s_to_ns(config.window_s)
            drives.append(_window(f'step{step:03d}_w{j}', sim.wheels, sim.truth, t0, t1, rng,
                                  config.truth_noise, step))
    return drives


def with_seed(config: WindowedConfig, seed: int) -> WindowedConfig:
    """Return the same recording plan with another seed (another draw of the commands)."""
    return replace(config, seed=seed)
