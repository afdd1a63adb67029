"""ROS 1 bags: the same drive as a rosbag2 and as a .bag (lz4 chunks) gives the same numbers.

The ROS 1 bag is written by rosbags' own converter from the rosbag2 the simulator wrote, with
ROS 1 Noetic's types (std_msgs/Header gains its seq): what a shelf of old bags holds.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from rosbags.convert.converter import convert
from rosbags.rosbag1 import Writer as Writer1

from skidkin_ros.adapters.bag_reader import open_recording
from skidkin_ros.adapters.bags.open import ros1_fallback_store
from skidkin_ros.adapters.sim_writer import write_bag
from skidkin_ros.cli.main import main
from skidkin_ros.core.odometry.config import read_params_file
from skidkin_ros.errors import RecordingError
from skidkin_ros.sim import LidarConfig, SimConfig, simulate

LIDAR = LidarConfig(azimuth_resolution_deg=2.0)
JOINTS = ['left_wheel', 'right_wheel']


def write_ros1_copy(rosbag2: Path, target: Path, compress: str | None = 'lz4') -> Path:
    """Write the messages of a rosbag2 as a ROS 1 bag with rosbags' converter."""
    convert([rosbag2], target, '', 0, compress, 'file', None, ros1_fallback_store(), [], [], [],
            [])
    return target


@pytest.fixture(scope='module')
def drives(tmp_path_factory):
    folder = tmp_path_factory.mktemp('ros1')
    sim = simulate(SimConfig(duration_s=60.0, seed=8, lidar=LIDAR, internal_rate_hz=200.0))
    bag2, _ = write_bag(sim, folder / 'drive')
    bag1 = write_ros1_copy(bag2, folder / 'drive.bag')
    return bag2, bag1


def _read_all(path):
    with open_recording(path) as rec:
        wheels = rec.read_wheels()
        imu = rec.read_imu()
        extrinsic = rec.read_extrinsic('base_link', next(rec.iter_lidar()).frame_id)
        frames = list(rec.iter_lidar(start_ns=None, stop_ns=None))[:5]
        return wheels, imu, extrinsic, frames, rec.summary(), rec.format


def test_a_ros1_bag_with_lz4_chunks_decodes_to_the_same_values(drives):
    bag2, bag1 = drives
    assert b'compression=lz4' in bag1.read_bytes()  # chunks really are lz4
    w2, i2, e2, f2, s2, kind2 = _read_all(bag2)
    w1, i1, e1, f1, s1, kind1 = _read_all(bag1)
    assert (kind2, kind1) == ('rosbag2', 'rosbag1')
    for a, b in ((w2, w1), (i2, i1)):
        for name in a.__dataclass_fields__:
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_array_equal(e2, e1)
    assert len(f2) == len(f1) == 5
    for a, b in zip(f2, f1):
        assert (a.stamp_ns, a.end_ns, a.frame_id) == (b.stamp_ns, b.end_ns, b.frame_id)
        np.testing.assert_array_equal(a.xyz, b.xyz)
        np.testing.assert_array_equal(a.t_rel_s, b.t_rel_s)
    assert s2 == s1  # topics, types, counts and receive-time ranges


def _rows(path):
    with open(path, newline='') as handle:
        return list(csv.DictReader(handle))


@pytest.mark.heavy
def test_groundtruth_calibrate_and_predict_agree_exactly_on_both_formats(drives, tmp_path,
                                                                         capsys):
    outputs = {}
    printed = {}
    for name, bag in zip(('rosbag2', 'rosbag1'), drives):
        out = tmp_path / name
        out.mkdir()
        common = ['--no-cache', '--no-progress', '--jobs', '1']
        assert main(['groundtruth', str(bag), '--out', str(out / 'gt.csv')] + common) == 0
        assert main(['calibrate', str(bag), '--out', str(out / 'params.yaml'),
                     '--models', 'edd_symmetric', 'edd_asymmetric', '--starts', '2',
                     '--accept-invalid'] + common) == 0
        assert main(['predict', str(bag), '--params', str(out / 'params.yaml'),
                     '--out', str(out / 'pred.csv')]) == 0
        capsys.readouterr()
        assert main(['evaluate', str(bag), '--params', str(out / 'params.yaml'),
                     '--models', 'edd_symmetric', 'edd_asymmetric'] + common) == 0
        printed[name] = (capsys.readouterr().out.replace(str(out), 'OUT')
                         .replace(str(bag), 'BAG').replace(bag.name, 'BAG'))
        outputs[name] = out
    a, b = outputs['rosbag2'], outputs['rosbag1']
    assert (a / 'gt.csv').read_text() == (b / 'gt.csv').read_text()
    assert len(_rows(a / 'gt.csv')) > 50
    pa, pb = read_params_file(a / 'params.yaml'), read_params_file(b / 'params.yaml')
    fitted = {k: v for k, v in pa.items() if k.startswith('models.')}
    assert fitted and fitted == {k: v for k, v in pb.items() if k.startswith('models.')}
    assert (a / 'pred.csv').read_text() == (b / 'pred.csv').read_text()
    assert 'edd_asymmetric' in printed['rosbag2']
    assert printed['rosbag2'] == printed['rosbag1']  # evaluate's error table, digit for digit


def _write_ros1(path, definition, md5, msgtype='sensor_msgs/msg/JointState'):
    """Write a ROS 1 bag whose /joint_states carries ``definition`` / ``md5`` and a good /imu."""
    store = ros1_fallback_store()
    Header = store.types['std_msgs/msg/Header']
    Time = store.types['builtin_interfaces/msg/Time']
    JointState = store.types['sensor_msgs/msg/JointState']
    with Writer1(path) as writer:
        joints = writer.add_connection('/joint_states', msgtype, msgdef=definition, md5sum=md5)
        imu_conn = writer.add_connection('/imu', 'sensor_msgs/msg/Imu', typestore=store)
        imu_type = store.types['sensor_msgs/msg/Imu']
        vec = store.types['geometry_msgs/msg/Vector3']
        quat = store.types['geometry_msgs/msg/Quaternion']
        for i in range(20):
            t_ns = 1_700_000_000_000_000_000 + i * 10_000_000
            header = Header(seq=i, stamp=Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9),
                            frame_id='base_link')
            msg = JointState(header=header, name=JOINTS, position=np.zeros(2),
                             velocity=np.array([1.0, 2.0]), effort=np.zeros(0))
            writer.write(joints, t_ns, store.serialize_ros1(msg, 'sensor_msgs/msg/JointState'))
            imu = imu_type(header=header, orientation=quat(x=0.0, y=0.0, z=0.0, w=1.0),
                           orientation_covariance=np.zeros(9),
                           angular_velocity=vec(x=0.0, y=0.0, z=0.1),
                           angular_velocity_covariance=np.zeros(9),
                           linear_acceleration=vec(x=0.0, y=0.0, z=9.8),
                           linear_acceleration_covariance=np.zeros(9))
            writer.write(imu_conn, t_ns, store.serialize_ros1(imu, 'sensor_msgs/msg/Imu'))
    return path


def test_a_missing_definition_with_noetics_md5_falls_back_to_noetic(tmp_path):
    md5 = ros1_fallback_store().generate_msgdef('sensor_msgs/msg/JointState')[1]
    bag = _write_ros1(tmp_path / 'nodef.bag', '', md5)
    with open_recording(bag) as rec:
        wheels = rec.read_wheels()
        assert any("matches ROS 1 Noetic's" in n for n in rec.notes)
    np.testing.assert_array_equal(wheels.omega_l, 1.0)
    np.testing.assert_array_equal(wheels.omega_r, 2.0)


@pytest.mark.parametrize('definition, md5, expected', [
    ('', '0123456789abcdef0123456789abcdef', 'stores no message definition'),
    ('%%% garbage', '0123456789abcdef0123456789abcdef',
     'stored definition cannot be used'),
    ('float64 left\nfloat64 right', '0123456789abcdef0123456789abcdef',
     'does not match its md5'),
])
def test_c110_a_ros1_topic_whose_definition_is_unknown_is_refused_by_name(
        tmp_path, definition, md5, expected):
    bag = _write_ros1(tmp_path / 'bad.bag', definition, md5)
    with open_recording(bag) as rec:
        imu = rec.read_imu()  # the other topics still read
        assert len(imu.t_ns) == 20
        with pytest.raises(RecordingError) as err:
            rec.read_wheels()
    text = str(err.value)
    assert expected in text and '/joint_states' in text and 'sensor_msgs/msg/JointState' in text
    assert '--msg-file' in text


def test_c110_a_msg_file_makes_a_custom_ros1_type_readable(tmp_path):
    definition = ros1_fallback_store().generate_msgdef('sensor_msgs/msg/JointState')[0]
    own = tmp_path / 'my_msgs' / 'msg' / 'WheelState.msg'
    own.parent.mkdir(parents=True)
    own.write_text(definition.split('\n' + '=' * 80)[0])
    bag = _write_ros1(tmp_path / 'custom.bag', '', '0123456789abcdef0123456789abcdef',
                      msgtype='my_msgs/msg/WheelState')
    with open_recording(bag) as rec:
        with pytest.raises(RecordingError, match='cannot be decoded'):
            list(rec.messages('/joint_states'))
    with open_recording(bag, msg_files=[own]) as rec:
        msgs = [m for _, m in rec.messages('/joint_states')]
    assert len(msgs) == 20 and list(msgs[0].velocity) == [1.0, 2.0]


def test_c111_a_truncated_or_foreign_bag_file_is_a_clear_error(drives, tmp_path, capsys):
    _, bag1 = drives
    cut = tmp_path / 'cut.bag'
    cut.write_bytes(bag1.read_bytes()[: bag1.stat().st_size // 2])
    with pytest.raises(RecordingError, match='rosbag reindex'):
        open_recording(cut)
    foreign = tmp_path / 'notes.bag'
    foreign.write_text('shopping list\n')
    code = main(['groundtruth', str(foreign), '--out', str(tmp_path / 'gt.csv')])
    err = capsys.readouterr().err
    assert code != 0 and 'cannot open ROS 1 bag' in err and 'Traceback' not in err


def test_a_folder_of_split_ros1_bags_reads_as_one_recording(drives, tmp_path):
    bag2, _ = drives
    folder = tmp_path / 'split'
    folder.mkdir()
    # Two halves by topic (rosbag record --split cuts by size; by topic is the simplest cut).
    convert([bag2], folder / 'a_0.bag', '', 0, 'lz4', 'file', None, ros1_fallback_store(), [],
            ['/joint_states', '/tf_static'], [], [])
    convert([bag2], folder / 'a_1.bag', '', 0, None, 'file', None, ros1_fallback_store(), [],
            ['/imu'], [], [])
    with open_recording(folder) as rec, open_recording(bag2) as whole:
        assert rec.format == 'rosbag1' and len(rec.files) == 2
        np.testing.assert_array_equal(rec.read_wheels().omega_l, whole.read_wheels().omega_l)
        np.testing.assert_array_equal(rec.read_imu().yaw_rate, whole.read_imu().yaw_rate)


@pytest.mark.heavy
def test_c114_groundtruth_reads_a_bag_without_wheels_and_says_the_check_is_skipped(
        drives, tmp_path, capsys):
    bag2, _ = drives
    # Lidar, IMU and tf_static only: the drive's JointState left out.
    no_wheels = tmp_path / 'no_wheels.bag'
    convert([bag2], no_wheels, '', 0, 'lz4', 'file', None, ros1_fallback_store(),
            ['/joint_states'], [], [], [])
    common = ['--no-cache', '--no-progress', '--jobs', '1']
    assert main(['groundtruth', str(no_wheels), '--out', str(tmp_path / 'a.csv')] + common) == 0
    printed = capsys.readouterr()
    out = printed.out + printed.err
    assert 'no wheel input' in out and 'wheel check is skipped' in out
    assert main(['groundtruth', str(bag2), '--out', str(tmp_path / 'b.csv')] + common) == 0
    a, b = _rows(tmp_path / 'a.csv'), _rows(tmp_path / 'b.csv')
    assert len(a) == len(b) > 50
    for name in ('t_ns', 'x', 'y', 'yaw'):  # the wheels only ever judge, never move a pose
        assert [r[name] for r in a] == [r[name] for r in b]
    # calibrate still needs the wheels: the same bag is refused there, with the topics listed.
    code = main(['calibrate', str(no_wheels), '--out', str(tmp_path / 'p.yaml')] + common)
    err = capsys.readouterr().err
    assert code != 0 and 'no sensor_msgs/msg/JointState topic' in err and '/points' in err
