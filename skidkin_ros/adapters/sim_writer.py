"""Write a simulation out: the rosbag2 a robot would have recorded, and its true trajectory.

The simulator (:mod:`skidkin_ros.sim`) only produces data in memory; this adapter streams it into
a rosbag2 (sqlite3 or mcap) through :class:`~skidkin_ros.adapters.bag_writer.BagWriter`, one lidar
sweep at a time with the wheel, IMU and truth messages in receive-time order, and writes the truth
at the wheel stamps as a trajectory table (the columns :mod:`skidkin_ros.adapters.table` reads).

Example::

    from skidkin_ros.adapters.sim_writer import write_bag
    from skidkin_ros.sim import SimConfig, simulate

    bag, truth_csv = write_bag(simulate(SimConfig(duration_s=60.0)), Path('drive'))
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from skidkin_ros.adapters.bag_writer import BagWriter
from skidkin_ros.atomic import atomic_write_text
from skidkin_ros.core.odometry.se2 import wrap_angle
from skidkin_ros.core.rotation import yaw_to_quaternion
from skidkin_ros.core.timeunits import s_to_ns, s_to_ns_array
from skidkin_ros.errors import ParameterError
from skidkin_ros.sim.lidar import LidarScan
from skidkin_ros.sim.simulate import JOINT_NAMES, Simulation

__all__ = ['POINT_TIME_CONVENTIONS', 'write_bag', 'write_truth_csv']

# Per-point time conventions of write_bag: name -> (field name, dtype, meaning).
POINT_TIME_CONVENTIONS: dict[str, tuple[str, str, str]] = {
    'rel_s_f32': ('t', 'float32', 'seconds after header.stamp'),
    'time_rel_s_f32': ('time', 'float32', 'seconds after header.stamp (velodyne driver)'),
    'rel_ns_u32': ('t', 'uint32', 'nanoseconds after header.stamp (ouster driver)'),
    'abs_s_f64': ('timestamp', 'float64', 'absolute seconds (hesai/livox style)'),
    'none': ('', '', 'no per-point time field'),
}
GRAVITY_M_S2 = 9.80665


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
        return s_to_ns_array(rel_s).astype(np.uint32), stamp_ns
    if convention == 'abs_s_f64':
        return scan.stamp_ns * 1e-9 + scan.t_rel_s, stamp_ns
    return None, stamp_ns


def write_bag(sim: Simulation, path: Path, storage: str = 'sqlite3', overwrite: bool = False,
              point_time: str = 'rel_s_f32', stamp_at: str = 'start',
              lidar_latency_s: float = 0.01, truth_csv: Path | None = None,
              truth_topic: str | None = None, topics: Mapping[str, str] | None = None,
              wrap_positions: bool = False) -> tuple[Path, Path]:
    """Stream the simulation into a rosbag2 and the truth into a CSV; return both paths.

    Topics (override with ``topics``): /joint_states (4 wheel joints, measured speeds, joint
    angles), /points (PointCloud2 in frame 'lidar', per-point times after ``point_time``:
    see POINT_TIME_CONVENTIONS; header.stamp at the sweep start, or at its end with
    ``stamp_at='end'`` and negative relative times), /imu (base_link), /tf_static
    (base_link -> lidar), and, with ``truth_topic``, the truth as nav_msgs/Odometry. Clouds are
    received ``lidar_latency_s`` after the sweep ends; messages are written in receive-time
    order, one sweep at a time. The CSV defaults to ``<bag>_truth.csv`` beside the bag.
    ``wrap_positions``: write the joint angles wrapped into [-pi, pi), as some drivers of
    continuous joints do (default: the integrated angle).
    """
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
    latency_ns = s_to_ns(lidar_latency_s)
    small = _small_messages(sim, names, truth_topic)
    cursor = 0
    with BagWriter(path, storage=storage, overwrite=overwrite) as writer:
        writer.write_tf_static(sim.start_ns, 'base_link', lidar.frame_id,
                               list(lidar.mount_xyz_m),
                               list(yaw_to_quaternion(lidar.mount_yaw_rad)))
        for scan in sim.scans():
            receive_ns = scan.end_ns + latency_ns
            while cursor < len(small) and small[cursor][0] <= receive_ns:
                _write_small(writer, sim, small[cursor], wrap_positions)
                cursor += 1
            values, stamp_ns = _point_times(scan, point_time, stamp_at)
            writer.write_pointcloud(names['points'], receive_ns, scan.frame_id, scan.xyz,
                                    t_point=values, time_field=field_name or 't',
                                    time_dtype=dtype or 'float32', stamp_ns=stamp_ns,
                                    extra_fields={'ring': scan.ring})
        for item in small[cursor:]:
            _write_small(writer, sim, item, wrap_positions)
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


def _write_small(writer: BagWriter, sim: Simulation, item: tuple[int, str, int, str],
                 wrap_positions: bool = False) -> None:
    t_ns, kind, i, topic = item
    if kind == 'joint_states':
        left, right = float(sim.wheels.omega_l[i]), float(sim.wheels.omega_r[i])
        pos_l, pos_r = float(sim.wheel_pos_l[i]), float(sim.wheel_pos_r[i])
        if wrap_positions:
            pos_l, pos_r = (float(wrap_angle(pos)) for pos in (pos_l, pos_r))
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
