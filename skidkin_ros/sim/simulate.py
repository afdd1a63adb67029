"""Simulate a skid-steer drive: wheel encoders, IMU, a spinning lidar, and the exact truth.

``simulate(config)`` returns a :class:`Simulation` held in memory (wheel samples with noisy
measured speeds, the true poses on the fine grid and at every sample, IMU samples) and yields
lidar sweeps lazily (``Simulation.scans()``). The simulator only produces data: writing it as a
rosbag2 and its truth as a trajectory table is :mod:`skidkin_ros.adapters.sim_writer`'s job.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
import logging
import math
from typing import Iterator, Mapping

import numpy as np

from skidkin_ros.core.drive import Drive, ImuSamples, PoseTrack, WheelSamples
from skidkin_ros.core.kinematics.models import BoundModel, get_model
from skidkin_ros.core.kinematics.specs import DEFAULT_GEOMETRY, Geometry
from skidkin_ros.core.timeunits import NS_PER_S
from skidkin_ros.errors import ParameterError
from skidkin_ros.sim.effects import Effect
from skidkin_ros.sim.lidar import cast_sweep, LidarConfig, LidarScan
from skidkin_ros.sim.robot import (CommandSchedule, plan_commands, scripted_commands, true_motion,
                                   TruthTrace)
from skidkin_ros.sim.scene import make_scene, Scene, SCENE_NAMES

__all__ = ['DEFAULT_TRUE_PARAMS', 'JOINT_NAMES', 'SimConfig', 'Simulation', 'simulate']

_LOG = logging.getLogger(__name__)

DEFAULT_TRUE_PARAMS: dict[str, float] = {
    'alpha_l': 0.9, 'alpha_r': 0.85, 'x_v': -0.05, 'y_l': 0.5, 'y_r': -0.55}
JOINT_NAMES: tuple[str, ...] = ('front_left_wheel_joint', 'rear_left_wheel_joint',
                                'front_right_wheel_joint', 'rear_right_wheel_joint')


@dataclass(frozen=True)
class SimConfig:
    """Everything that defines a simulated drive; the same config and seed give the same drive.

    Rates in Hz, times in s, speeds in rad/s, lengths in m. ``true_model``/``true_params`` set
    the true kinematics (applied to the actual wheel speeds); ``effects`` add departures from
    it. The robot plans its commands to stay within ``arena_radius_m`` of the start, unless
    ``script`` gives the commands: (hold_s, omega_l, omega_r) triples after the initial rest,
    the last one held to the end (the caller keeps such a drive inside the scene). ``scene``:
    'courtyard' (walls, boxes, pillars) or 'forest' (an open field with 400 trees, see
    :func:`skidkin_ros.sim.scene.outdoor_scene`); the robot drives in the obstacle-free disc of
    radius 0.55 ``scene_half_size_m`` of either.
    """

    duration_s: float = 60.0
    seed: int = 0
    wheel_radius: float = DEFAULT_GEOMETRY.wheel_radius
    track_width: float = DEFAULT_GEOMETRY.track_width
    true_model: str = 'edd_asymmetric'
    true_params: Mapping[str, float] = field(
        default_factory=lambda: dict(DEFAULT_TRUE_PARAMS))
    effects: tuple[Effect, ...] = ()
    wheel_rate_hz: float = 20.0
    imu_rate_hz: float = 100.0
    internal_rate_hz: float = 1000.0
    max_wheel_speed_rad_s: float = 6.0
    hold_range_s: tuple[float, float] = (2.0, 4.0)
    initial_rest_s: float = 1.0
    motor_tau_s: float = 0.12
    encoder_noise_rad_s: float = 0.05
    gyro_noise_rad_s: float = 0.005
    accel_noise_m_s2: float = 0.05
    arena_radius_m: float = 5.0
    start_ns: int = 1_700_000_000_000_000_000
    lidar: LidarConfig = field(default_factory=LidarConfig)
    scene_half_size_m: float = 14.0
    script: tuple[tuple[float, float, float], ...] = ()
    scene: str = 'courtyard'

    def __post_init__(self) -> None:
        checks = (
            ('duration_s', 1.0, 3600.0), ('wheel_rate_hz', 1.0, 1000.0),
            ('imu_rate_hz', 1.0, 2000.0), ('internal_rate_hz', 100.0, 20000.0),
            ('max_wheel_speed_rad_s', 0.1, 100.0), ('initial_rest_s', 0.0, 60.0),
            ('motor_tau_s', 0.0, 5.0), ('encoder_noise_rad_s', 0.0, 10.0),
            ('gyro_noise_rad_s', 0.0, 10.0), ('accel_noise_m_s2', 0.0, 100.0),
            ('arena_radius_m', 0.5, 1000.0), ('scene_half_size_m', 2.0, 1000.0))
        for name, low, high in checks:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and low <= value <= high):
                raise ParameterError(f'SimConfig.{name} must be in [{low:g}, {high:g}], got '
                                     f'{value!r}')
        if self.scene not in SCENE_NAMES:
            raise ParameterError(f'SimConfig.scene must be one of {SCENE_NAMES}, got '
                                 f'{self.scene!r}')
        low, high = self.hold_range_s
        if not 0.1 <= low <= high:
            raise ParameterError('SimConfig.hold_range_s must be (low, high) s with '
                                 f'0.1 <= low <= high, got {self.hold_range_s!r}')
        if self.arena_radius_m > 0.5 * self.scene_half_size_m:
            raise ParameterError('SimConfig.arena_radius_m must stay within half the scene '
                                 f'half size ({0.5 * self.scene_half_size_m:g} m) so the '
                                 'robot keeps clear of the obstacles')
        for item in self.script:
            if (len(item) != 3 or not all(isinstance(v, (int, float)) and math.isfinite(v)
                                          for v in item) or item[0] <= 0.0):
                raise ParameterError('SimConfig.script items must be (hold_s > 0, omega_l, '
                                     f'omega_r) in s, rad/s, rad/s; got {item!r}')
        for effect in self.effects:
            if not isinstance(effect, Effect):
                raise ParameterError('SimConfig.effects must hold sim.effects.Effect objects '
                                     '(use make_effect(name, strength))')
        self.bound_model()  # validates the true model and parameters

    @property
    def geometry(self) -> Geometry:
        return Geometry(self.wheel_radius, self.track_width)

    def bound_model(self) -> BoundModel:
        """Return the true kinematic model with its true parameters."""
        return get_model(self.true_model).bind(dict(self.true_params), self.geometry)

    def as_dict(self) -> dict:
        """Return a plain dict for provenance (effects as name/strength dicts)."""
        out = asdict(self)
        out['true_params'] = dict(self.true_params)
        out['effects'] = [effect.as_dict() for effect in self.effects]
        return out


def _sample_times(start_ns: int, duration_s: float, rate_hz: float) -> np.ndarray:
    count = int(math.floor(duration_s * rate_hz + 1e-9)) + 1
    return start_ns + np.round(np.arange(count) * (NS_PER_S / rate_hz)).astype(np.int64)


@dataclass(frozen=True)
class Simulation:
    """A simulated drive in memory; lidar sweeps are produced lazily by :meth:`scans`.

    wheels: measured (noisy) speeds at the wheel rate; wheels_true: the actual speeds at the
    same stamps; wheel_cmd_*: commands in force; wheel_pos_*: integrated joint angles (rad);
    truth: true base_link poses at the wheel stamps; trace: the fine-grid truth (poses at every
    internal step); imu: gyro z and body accelerations.
    """

    config: SimConfig
    schedule: CommandSchedule
    trace: TruthTrace
    wheels: WheelSamples
    wheels_true: WheelSamples
    wheel_cmd_l: np.ndarray
    wheel_cmd_r: np.ndarray
    wheel_pos_l: np.ndarray
    wheel_pos_r: np.ndarray
    truth: PoseTrack
    imu: ImuSamples
    scene: Scene

    @property
    def start_ns(self) -> int:
        return int(self.trace.t_ns[0])

    @property
    def end_ns(self) -> int:
        return int(self.trace.t_ns[-1])

    def pose_at(self, t_ns) -> np.ndarray:
        """Return true base poses (..., 3) at the given stamps (interpolated on the fine grid)."""
        t = np.asarray(t_ns, dtype=np.int64)
        ref = self.trace.t_ns
        poses = self.trace.poses
        return np.stack([np.interp(t, ref, poses[:, 0]), np.interp(t, ref, poses[:, 1]),
                         np.interp(t, ref, poses[:, 2])], axis=-1)

    def truth_at(self, t_ns) -> PoseTrack:
        """Return the true track at the given stamps."""
        poses = self.pose_at(t_ns)
        return PoseTrack(np.asarray(t_ns, dtype=np.int64), poses[:, 0], poses[:, 1],
                         poses[:, 2])

    def sweep_starts_ns(self) -> np.ndarray:
        """Return the start stamps of the lidar sweeps that fit entirely in the drive."""
        period = self.config.lidar.period_ns
        count = (self.end_ns - self.start_ns) // period
        return self.start_ns + np.arange(count, dtype=np.int64) * period

    def scans(self, seed_offset: int = 1) -> Iterator[LidarScan]:
        """Yield the lidar sweeps one by one (deterministic for the config seed)."""
        rng = np.random.default_rng([self.config.seed, seed_offset])
        for start in self.sweep_starts_ns():
            yield cast_sweep(self.scene, self.config.lidar, self.pose_at, int(start), rng)

    def drive(self, name: str = 'sim') -> Drive:
        """Return the core Drive: measured wheels, truth at the wheel stamps, IMU."""
        meta = {'source': 'skidkin_ros.sim', 'config': self.config.as_dict(),
                'cmd_left': self.wheel_cmd_l, 'cmd_right': self.wheel_cmd_r}
        return Drive(name, self.wheels, self.truth, self.imu, meta)


def simulate(config: SimConfig | None = None) -> Simulation:
    """Simulate a drive (wheels, IMU, truth); lidar sweeps come from ``Simulation.scans()``."""
    config = config or SimConfig()
    rng = np.random.default_rng(config.seed)
    model = config.bound_model()
    fine_t = _sample_times(config.start_ns, config.duration_s, config.internal_rate_hz)
    if config.script:
        schedule = scripted_commands(config.start_ns, config.initial_rest_s, config.script)
    else:
        schedule = plan_commands(
            rng, config.start_ns, config.duration_s, fine_t, model, config.effects,
            config.motor_tau_s, config.max_wheel_speed_rad_s, tuple(config.hold_range_s),
            config.arena_radius_m, config.initial_rest_s)
    trace = true_motion(schedule, fine_t, model, config.effects, config.motor_tau_s,
                        config.duration_s)
    wheel_t = _sample_times(config.start_ns, config.duration_s, config.wheel_rate_hz)
    true_l = np.interp(wheel_t, fine_t, trace.omega_l)
    true_r = np.interp(wheel_t, fine_t, trace.omega_r)
    noise = rng.normal(0.0, config.encoder_noise_rad_s, (2, wheel_t.size))
    cmd_l, cmd_r = schedule.at(wheel_t)
    dt_fine = 1.0 / config.internal_rate_hz
    pos_l = np.interp(wheel_t, fine_t, np.concatenate([[0.0], np.cumsum(trace.omega_l)[:-1]]))
    pos_r = np.interp(wheel_t, fine_t, np.concatenate([[0.0], np.cumsum(trace.omega_r)[:-1]]))
    truth_poses = np.stack([np.interp(wheel_t, fine_t, trace.poses[:, i]) for i in range(3)],
                           axis=-1)
    scene = make_scene(config.scene, config.scene_half_size_m)
    sim = Simulation(
        config=config, schedule=schedule, trace=trace,
        wheels=WheelSamples(wheel_t, true_l + noise[0], true_r + noise[1]),
        wheels_true=WheelSamples(wheel_t, true_l, true_r),
        wheel_cmd_l=cmd_l, wheel_cmd_r=cmd_r, wheel_pos_l=pos_l * dt_fine,
        wheel_pos_r=pos_r * dt_fine,
        truth=PoseTrack(wheel_t, truth_poses[:, 0], truth_poses[:, 1], truth_poses[:, 2]),
        imu=_imu_samples(config, trace, rng), scene=scene)
    _check_inside(sim)
    return sim


def _imu_samples(config: SimConfig, trace: TruthTrace, rng: np.random.Generator) -> ImuSamples:
    """Return gyro z and body-frame accelerations (no gravity in x/y: the ground is level)."""
    t_s = (trace.t_ns - trace.t_ns[0]) * 1e-9
    v_x, v_y, omega = trace.twist[:, 0], trace.twist[:, 1], trace.twist[:, 2]
    accel_x = np.gradient(v_x, t_s) - omega * v_y
    accel_y = np.gradient(v_y, t_s) + omega * v_x
    imu_t = _sample_times(config.start_ns, config.duration_s, config.imu_rate_hz)
    n = imu_t.size
    return ImuSamples(
        imu_t,
        np.interp(imu_t, trace.t_ns, omega) + rng.normal(0.0, config.gyro_noise_rad_s, n),
        np.interp(imu_t, trace.t_ns, accel_x) + rng.normal(0.0, config.accel_noise_m_s2, n),
        np.interp(imu_t, trace.t_ns, accel_y) + rng.normal(0.0, config.accel_noise_m_s2, n))


def _check_inside(sim: Simulation) -> None:
    """Warn when the true path left the obstacle-free part of the scene."""
    radius = np.hypot(sim.trace.poses[:, 0], sim.trace.poses[:, 1])
    limit = 0.55 * sim.config.scene_half_size_m
    if np.any(radius > limit):
        _LOG.warning('simulated robot left the obstacle-free disc (max %.2f m > %.2f m); the '
                     'lidar may see through obstacles', float(radius.max()), limit)
