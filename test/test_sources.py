"""Loading a SOURCE: the lidar extrinsic must come from /tf_static or the user (fault row C17)."""

import math

import numpy as np
import pytest
from skidkin_ros.adapters.bag_reader import open_recording
from skidkin_ros.adapters.bag_writer import BagWriter
from skidkin_ros.adapters.sources import extrinsic_from_xyz_rpy, load_source, SourceOptions
from skidkin_ros.errors import DataError

NAMES = ['front_left_wheel_joint', 'rear_left_wheel_joint', 'front_right_wheel_joint',
         'rear_right_wheel_joint']


def _bag_without_tf_static(path):
    rng = np.random.default_rng(0)
    t0 = 1_700_000_000_000_000_000
    with BagWriter(path) as bag:
        for i in range(40):
            bag.write_joint_state('/joint_states', t0 + i * 50_000_000, NAMES, [1.0] * 4)
        for i in range(3):
            xyz = rng.uniform(-10, 10, (500, 3))
            bag.write_pointcloud('/points', t0 + i * 100_000_000, 'lidar', xyz,
                                 np.linspace(0.0, 0.1, 500))
    return path


def test_missing_extrinsic_is_refused_with_the_remedy(tmp_path):
    bag = _bag_without_tf_static(tmp_path / 'bag')
    with pytest.raises(DataError) as err:
        load_source(bag, SourceOptions(ground_truth='icp'))
    text = str(err.value)
    assert '--extrinsic' in text and 'x_v' in text and "'lidar'" in text


def test_extrinsic_from_xyz_rpy_is_a_rigid_transform():
    t = extrinsic_from_xyz_rpy([0.3, -0.1, 0.5, 0.0, 0.0, np.pi / 2])
    np.testing.assert_allclose(t[:3, 3], [0.3, -0.1, 0.5])
    np.testing.assert_allclose(t[:3, :3] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-12)
    with pytest.raises(DataError, match='6 finite numbers'):
        extrinsic_from_xyz_rpy([0.0, 0.0, float('nan'), 0.0, 0.0, 0.0])


def _rx(a):
    return np.array([[1.0, 0.0, 0.0], [0.0, math.cos(a), -math.sin(a)],
                     [0.0, math.sin(a), math.cos(a)]])


def _ry(a):
    return np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0],
                     [-math.sin(a), 0.0, math.cos(a)]])


def _rz(a):
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0],
                     [0.0, 0.0, 1.0]])


def _quaternion_rpy(roll, pitch, yaw):
    """(x, y, z, w) of Rz(yaw) Ry(pitch) Rx(roll), as tf2's Quaternion.setRPY computes it."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)


RPY = (0.3, -0.7, 2.1)  # roll, pitch, yaw (rad): every axis, none of them special


def test_extrinsic_rpy_is_yaw_then_pitch_then_roll():
    """--extrinsic X Y Z ROLL PITCH YAW means Rz(yaw) Ry(pitch) Rx(roll), as URDF and tf2 do."""
    t = extrinsic_from_xyz_rpy([0.3, -0.1, 0.5, *RPY])
    np.testing.assert_allclose(t[:3, :3], _rz(RPY[2]) @ _ry(RPY[1]) @ _rx(RPY[0]),
                               rtol=0, atol=1e-15)
    np.testing.assert_allclose(t[3], [0.0, 0.0, 0.0, 1.0])


def test_tf_static_quaternion_becomes_the_same_rotation(tmp_path):
    with BagWriter(tmp_path / 'bag') as bag:
        q = _quaternion_rpy(*RPY)
        bag.write_tf_static(1, 'base_link', 'lidar', [0.3, -0.1, 0.5], [2.0 * v for v in q])
    with open_recording(tmp_path / 'bag') as bag:
        t = bag.read_extrinsic('base_link', 'lidar')
    np.testing.assert_allclose(t[:3, :3], _rz(RPY[2]) @ _ry(RPY[1]) @ _rx(RPY[0]),
                               rtol=0, atol=1e-15)
    np.testing.assert_allclose(t[:3, 3], [0.3, -0.1, 0.5])
    np.testing.assert_allclose(t, extrinsic_from_xyz_rpy([0.3, -0.1, 0.5, *RPY]), atol=1e-15)


def test_c30_wheel_spikes_are_blamed_on_the_wheels_not_the_lidar_ground_truth(tmp_path):
    """Red-team case: 90 rad/s spikes got most lidar frames flagged and blamed on the lidar."""
    from skidkin_ros.adapters.lidar_gt import IcpConfig
    from skidkin_ros.adapters.sim_writer import write_bag
    from skidkin_ros.sim import LidarConfig, SimConfig, simulate
    lidar = LidarConfig(azimuth_resolution_deg=0.5, mount_xyz_m=(0.3, 0.1, 0.5))
    sim = simulate(SimConfig(duration_s=15.0, seed=1, lidar=lidar))
    spikes = np.arange(5, len(sim.wheels), 10)  # twice a second on the right wheel (20 Hz)
    sim.wheels.omega_r[spikes] = 90.0           # under max_wheel_speed (100 rad/s)
    bag, _ = write_bag(sim, tmp_path / 'spiky')
    options = SourceOptions(cache_dir=None, icp=IcpConfig(voxel_size_m=0.5, max_range_m=50.0))
    loaded = load_source(bag, options)
    frames = loaded.truth_info['frames']
    assert frames.get('wheel_gross', 0) <= 2, frames  # 148 of 150 flagged by the old guard
    assert loaded.drives[0].truth.valid.mean() > 0.95
    note = next(n for n in loaded.notes if 'jumped' in n)
    assert f'dropped {spikes.size} of {len(sim.wheels)}' in note
    assert f'{spikes.size} on the right wheel' in note and 'not the lidar' in note
    assert np.abs(loaded.drives[0].wheels.omega_r).max() < 20.0
