"""Simulate a skid-steer drive: wheel encoders, IMU, a spinning lidar, and the exact truth.

``simulate(config)`` returns a :class:`Simulation` held in memory (wheel samples with noisy
measured speeds, the true poses on the fine grid and at every sample, IMU samples) and yields
lidar sweeps lazily (``Simulation.scans()``). ``write_bag`` streams it all into a rosbag2
(sqlite3 or mcap) through :class:`skidkin_ros.adapters.bag_writer.BagWriter` and writes the true
trajectory as a CSV beside the bag (the columns of the project's trajectory table).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
import logging
import math
from pathlib import Path
from typing import Iterator, Mapping

import numpy as np

from skidkin_ros.atomic import atomic_write_text
from skidkin_ros.core.drive import Drive, ImuSamples, PoseTrack, WheelSamples
from skidkin_ros.core.kinematics.models import BoundModel, get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.errors import ParameterError
from skidkin_ros.sim.effects import Effect
from skidkin_ros.sim.lidar import cast_sweep, LidarConfig, LidarScan
from skidkin_ros.sim.robot import (CommandSchedule, plan_commands, scripted_commands, true_motion,
                                   TruthTrace)
from skidkin_ros.sim.scene import default_scene, Scene

__all__ = ['DEFAULT_TRUE_PARAMS', 'JOINT_NAMES', 'POINT_TIME_CONVENTIONS', 'SimConfig',
           'Simulation', 'simulate', 'write_bag', 'write_truth_csv']

_LOG = logging.getLogger(__name__)

DEFAULT_TRUE_PARAMS: dict[str, float] = {
    'alpha_l': 0.9, 'alpha_r': 0.85, 'x_v': -0.05, 'y_l': 0.5, 'y_r': -0.55}
JOINT_NAMES: tuple[str, ...] = ('front_left_wheel_joint', 'rear_left_wheel_joint',
                                'front_right_wheel_joint', 'rear_right_wheel_joint')
# Per-point time conventions of write_bag: name -> (field name, dtype, meaning).
POINT_TIME_CONVENTIONS: dict[str, tuple[str, str, str]] = {
    'rel_s_f32': ('t', 'float32', 'seconds after header.stamp'),
    'time_rel_s_f32': ('time', 'float32', 'seconds after header.stamp (velodyne driver)'),
    'rel_ns_u32': ('t', 'uint32', 'nanoseconds after header.stamp (ouster driver)'),
    'abs_s_f64': ('timestamp', 'float64', 'absolute seconds (hesai/livox style)'),
    'none': ('', '', 'no per-point time field'),
}
GRAVITY_M_S2 = 9.80665


@dataclass(frozen=True)
class SimConfig:
    """Everything that defines a simulated drive; the same config and seed give the same drive.

    Rates in Hz, times in s, speeds in rad/s, lengths in m. ``true_model``/``true_params`` set
    the true kinematics (applied to the actual wheel speeds); ``effects`` add departures from
    it. The robot plans its commands to stay within ``arena_radius_m`` of the start, unless
    ``script`` gives the commands: (hold_s, omega_l, omega_r) triples after the initial rest,
    the last one held to the end (the caller keeps such a drive inside the scene).
    """

    duration_s: float = 60.0
    seed: int = 0
    wheel_radius: float = 0.1651
    track_width: float = 0.555
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
    return start_ns + np.round(np.arange(count) * (1e9 / rate_hz)).astype(np.int64)


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
    scene = default_scene(config.scene_half_size_m)
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


def write_truth_csv(sim: Simulation, path: Path, overwrite: bool = False) -> Path:
    """Write the truth at the wheel stamps as a trajectory table (columns of the table reader).

    Columns: t (s since the drive start), t_ns (absolute stamp), cmd_left, cmd_right,
    wheel_left, wheel_right (measured, rad/s), wheel_left_true, wheel_right_true (rad/s),
    x, y (m), yaw (rad, unwrapped), imu_yaw_rate (rad/s, true).
    """
    yaw_rate = np.interp(sim.wheels.t_ns, sim.trace.t_ns, sim.trace.twist[:, 2])
    header = ('t,t_ns,cmd_left,cmd_right,wheel_left,wheel_right,wheel_left_true,'
              'wheel_right_true,x,y,yaw,imu_yaw_rate')
    lines = [header]
    t0 = sim.wheels.t_ns[0]
    for i, t_ns in enumerate(sim.wheels.t_ns):
        values = (sim.wheel_cmd_l[i], sim.wheel_cmd_r[i], sim.wheels.omega_l[i],
                  sim.wheels.omega_r[i], sim.wheels_true.omega_l[i], sim.wheels_true.omega_r[i],
                  sim.truth.x[i], sim.truth.y[i], sim.truth.yaw[i], yaw_rate[i])
        lines.append(f'{(t_ns - t0) * 1e-9:.9f},{int(t_ns)},'
                     + ','.join(f'{value:.9g}' for value in values))
    return atomic_write_text(path, '\n'.join(lines) + '\n', force=overwrite)


def _point_times(scan: LidarScan, convention: str,
                 stamp_at: str) -> tuple[np.ndarray | None, int]:
    """Return (per-point time values in the convention, header stamp ns)."""
    stamp_ns = scan.stamp_ns if stamp_at == 'start' else scan.end_ns
    rel_s = scan.t_rel_s - (stamp_ns - scan.stamp_ns) * 1e-9
    if convention in ('rel_s_f32', 'time_rel_s_f32'):
        return rel_s.astype(np.float32), stamp_ns
    if convention == 'rel_ns_u32':
        return np.round(rel_s * 1e9).astype(np.uint32), stamp_ns
    if convention == 'abs_s_f64':
        return scan.stamp_ns * 1e-9 + scan.t_rel_s, stamp_ns
    return None, stamp_ns


def write_bag(sim: Simulation, path: Path, storage: str = 'sqlite3', overwrite: bool = False,
              point_time: str = 'rel_s_f32', stamp_at: str = 'start',
              lidar_latency_s: float = 0.01, truth_csv: Path | None = None,
              truth_topic: str | None = None, topics: Mapping[str, str] | None = None,
              ) -> tuple[Path, Path]:
    """Stream the simulation into a rosbag2 and the truth into a CSV; return both paths.

    Topics (override with ``topics``): /joint_states (4 wheel joints, measured speeds, joint
    angles), /points (PointCloud2 in frame 'lidar', per-point times after ``point_time``:
    see POINT_TIME_CONVENTIONS; header.stamp at the sweep start, or at its end with
    ``stamp_at='end'`` and negative relative times), /imu (base_link), /tf_static
    (base_link -> lidar), and, with ``truth_topic``, the truth as nav_msgs/Odometry. Clouds are
    received ``lidar_latency_s`` after the sweep ends; messages are written in receive-time
    order, one sweep at a time. The CSV defaults to ``<bag>_truth.csv`` beside the bag.
    """
    from skidkin_ros.adapters.bag_writer import BagWriter
    from skidkin_ros.core.rotation import yaw_to_quaternion

    if point_time not in POINT_TIME_CONVENTIONS:
        raise ParameterError(f'point_time must be one of {sorted(POINT_TIME_CONVENTIONS)}, '
                             f'got {point_time!r}')
    if stamp_at not in ('start', 'end'):
        raise ParameterError(f"stamp_at must be 'start' or 'end', got {stamp_at!r}")
    if stamp_at == 'end' and point_time == 'rel_ns_u32':
        raise ParameterError("stamp_at='end' gives negative relative times, which uint32 "
                             "cannot hold: use point_time='rel_s_f32' or 'abs_s_f64'")
    names = {'joint_states': '/joint_states', 'points': '/points', 'imu': '/imu'}
    names.update(topics or {})
    path = Path(path)
    csv_path = Path(truth_csv) if truth_csv else path.parent / f'{path.name}_truth.csv'
    field_name, dtype, _ = POINT_TIME_CONVENTIONS[point_time]
    lidar = sim.config.lidar
    latency_ns = int(round(lidar_latency_s * 1e9))
    small = _small_messages(sim, names, truth_topic)
    cursor = 0
    with BagWriter(path, storage=storage, overwrite=overwrite) as writer:
        writer.write_tf_static(sim.start_ns, 'base_link', lidar.frame_id,
                               list(lidar.mount_xyz_m),
                               list(yaw_to_quaternion(lidar.mount_yaw_rad)))
        for scan in sim.scans():
            receive_ns = scan.end_ns + latency_ns
            while cursor < len(small) and small[cursor][0] <= receive_ns:
                _write_small(writer, sim, small[cursor])
                cursor += 1
            values, stamp_ns = _point_times(scan, point_time, stamp_at)
            writer.write_pointcloud(names['points'], receive_ns, scan.frame_id, scan.xyz,
                                    t_point=values, time_field=field_name or 't',
                                    time_dtype=dtype or 'float32', stamp_ns=stamp_ns,
                                    extra_fields={'ring': scan.ring})
        for item in small[cursor:]:
            _write_small(writer, sim, item)
    write_truth_csv(sim, csv_path, overwrite=overwrite)
    return path, csv_path


def _small_messages(sim: Simulation, names: Mapping[str, str],
                    truth_topic: str | None) -> list[tuple[int, str, int, str]]:
    """Return (receive ns, kind, index, topic) of every non-lidar message, in time order."""
    items = [(int(t), 'joint_states', i, names['joint_states'])
             for i, t in enumerate(sim.wheels.t_ns)]
    items += [(int(t), 'imu', i, names['imu']) for i, t in enumerate(sim.imu.t_ns)]
    if truth_topic:
        items += [(int(t), 'truth', i, truth_topic) for i, t in enumerate(sim.truth.t_ns)]
    items.sort(key=lambda item: (item[0], item[1]))
    return items


def _write_small(writer, sim: Simulation, item: tuple[int, str, int, str]) -> None:
    t_ns, kind, i, topic = item
    if kind == 'joint_states':
        left, right = float(sim.wheels.omega_l[i]), float(sim.wheels.omega_r[i])
        pos_l, pos_r = float(sim.wheel_pos_l[i]), float(sim.wheel_pos_r[i])
        writer.write_joint_state(topic, t_ns, JOINT_NAMES, [left, left, right, right],
                                 positions=[pos_l, pos_l, pos_r, pos_r])
    elif kind == 'imu':
        imu = sim.imu
        writer.write_imu(topic, t_ns, 'base_link', [0.0, 0.0, float(imu.yaw_rate[i])],
                         [float(imu.accel_x[i]), float(imu.accel_y[i]), GRAVITY_M_S2])
    else:
        truth = sim.truth
        writer.write_odometry(topic, t_ns, 'odom', 'base_link', float(truth.x[i]),
                              float(truth.y[i]), float(truth.yaw[i]))
