"""bag_reader: real bags written by BagWriter into tmp_path, read back; faults C1-C8 and C19."""

from __future__ import annotations

import math
import os
import shutil
import sqlite3
import tracemalloc

import numpy as np
import pytest
from rosbags.typesys import get_types_from_msg, get_typestore, Stores

from skidkin_ros.adapters.bag_reader import (check_overlap, format_summary, keep_monotonic,
                                             open_recording, POINTCLOUD2)
from skidkin_ros.adapters.bag_writer import BagWriter
from skidkin_ros.core.rotation import yaw_to_quaternion
from skidkin_ros.errors import DataError, RecordingError

T0_NS = 1_700_000_000_000_000_000
MS = 1_000_000
JOINTS = ['front_left_wheel_joint', 'rear_left_wheel_joint', 'front_right_wheel_joint',
          'rear_right_wheel_joint', 'lidar_tilt_joint']


def _storage_file(path):
    return next(p for p in path.iterdir() if p.suffix in ('.db3', '.mcap'))


def _drive_bag(path, storage='sqlite3', n=50, clouds=5, cloud_points=100):
    """Write wheels at 100 Hz (stamps 2 ms before receive), clouds at 10 Hz, imu, odom, tf."""
    rng = np.random.default_rng(7)
    with BagWriter(path, storage=storage) as bag:
        bag.write_tf_static(T0_NS, 'base_link', 'lidar_mount', [0.5, 0.0, 0.3],
                            yaw_to_quaternion(math.pi / 2))
        bag.write_tf_static(T0_NS, 'os_lidar', 'lidar_mount', [0.0, 0.0, -0.1],
                            [0.0, 0.0, 0.0, 1.0])
        for i in range(n):
            t = T0_NS + i * 10 * MS
            bag.write_joint_state('/joint_states', t, JOINTS, [1.0, 3.0, 2.0, 2.0, 9.0],
                                  stamp_ns=t - 2 * MS)
            bag.write_imu('/imu', t, 'imu', [0.0, 0.0, 0.01 * i], [0.1, 0.2, 9.8])
            yaw = 0.2 * i  # crosses pi: must come back unwrapped
            bag.write_odometry('/odom', t, 'odom', 'base_link', 0.01 * i, 0.0, yaw)
            if i % (n // clouds) == 0:
                xyz = rng.uniform(-10, 10, (cloud_points, 3))
                t_point = np.linspace(0, 0.1, cloud_points)
                bag.write_pointcloud('/points', t, 'os_lidar', xyz, t_point=t_point)
    return path


@pytest.fixture(scope='module')
def drive_bag(tmp_path_factory):
    return _drive_bag(tmp_path_factory.mktemp('bags') / 'drive')


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_reads_every_kind_in_both_storages(tmp_path, storage):
    path = _drive_bag(tmp_path / 'bag', storage)
    with open_recording(path) as bag:
        wheels = bag.read_wheels()
        assert len(wheels) == 50
        assert wheels.t_ns[0] == T0_NS - 2 * MS  # header.stamp, not receive time
        np.testing.assert_allclose(wheels.omega_l, 2.0)  # mean of 1 and 3
        np.testing.assert_allclose(wheels.omega_r, 2.0)
        assert any('front_left_wheel_joint' in n and 'taken as left' in n for n in bag.notes)
        assert any('using /joint_states' in n for n in bag.notes)

        frames = list(bag.iter_lidar())
        assert len(frames) == 5
        frame = frames[1]
        assert frame.frame_id == 'os_lidar' and frame.xyz.shape == (100, 3)
        assert frame.stamp_ns == T0_NS + 100 * MS
        assert frame.end_ns == pytest.approx(frame.stamp_ns + 100 * MS, abs=10)
        np.testing.assert_allclose(frame.t_rel_s[[0, -1]], [0.0, 0.1], atol=1e-7)

        imu = bag.read_imu()
        np.testing.assert_allclose(imu.yaw_rate, 0.01 * np.arange(50))
        np.testing.assert_allclose(imu.accel_y, 0.2)

        track = bag.read_pose_track()
        np.testing.assert_allclose(track.yaw, 0.2 * np.arange(50), atol=1e-9)
        np.testing.assert_allclose(track.x, 0.01 * np.arange(50))


def test_extrinsic_chained_through_an_inverted_edge(drive_bag):
    with open_recording(drive_bag) as bag:
        matrix = bag.read_extrinsic('base_link', 'os_lidar')
        assert bag.read_extrinsic('base_link', 'camera') is None
        notes = list(bag.notes)
    # base -> mount: 0.5 m ahead, 0.3 m up, yawed 90 deg; mount -> lidar: 0.1 m up (inverted edge).
    np.testing.assert_allclose(matrix[:3, 3], [0.5, 0.0, 0.4], atol=1e-12)
    np.testing.assert_allclose(matrix[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    assert any('via base_link -> lidar_mount -> os_lidar' in n for n in notes)
    assert any('does not join base_link and camera' in n for n in notes)


def test_extrinsic_absent_is_none(tmp_path):
    with BagWriter(tmp_path / 'bag') as bag:
        bag.write_float64('/x', T0_NS, 1.0)
    with open_recording(tmp_path / 'bag') as bag:
        assert bag.read_extrinsic('base_link', 'lidar') is None
        assert any('no /tf_static' in n for n in bag.notes)


def test_summary_counts_and_time_ranges(drive_bag):
    with open_recording(drive_bag) as bag:
        items = {s.topic: s for s in bag.summary()}
    assert items['/joint_states'].count == 50
    assert items['/points'].msgtype == POINTCLOUD2 and items['/points'].count == 5
    assert items['/joint_states'].first_ns == T0_NS
    assert items['/joint_states'].last_ns == T0_NS + 490 * MS
    assert items['/joint_states'].duration_s == pytest.approx(0.49)
    text = format_summary(list(items.values()))
    assert '/imu  [sensor_msgs/msg/Imu]  50 msgs' in text


def test_named_joints_and_pose_stamped(tmp_path):
    with BagWriter(tmp_path / 'bag') as bag:
        for i in range(5):
            t = T0_NS + i * 10 * MS
            bag.write_joint_state('/js', t, ['a', 'b', 'c'], [1.0, 2.0, 4.0])
            bag.write_pose_stamped('/gt', t, 'map', float(i), 0.0, 0.0)
    with open_recording(tmp_path / 'bag') as bag:
        wheels = bag.read_wheels('/js', left_joints=['a'], right_joints=['b', 'c'])
        np.testing.assert_allclose(wheels.omega_r, 3.0)
        assert len(bag.read_pose_track('/gt')) == 5
        with pytest.raises(RecordingError, match=r"joints seen: \['a', 'b', 'c'\]"):
            bag.read_wheels('/js', left_joints=['left'], right_joints=['right'])
        with pytest.raises(RecordingError, match=r'joints named \*left\* / \*right\*'):
            bag.read_wheels('/js')


# -- C1 ------------------------------------------------------------------------------------------
def test_c1_missing_path(tmp_path):
    with pytest.raises(RecordingError, match='nowhere.*does not exist'):
        open_recording(tmp_path / 'nowhere')


def test_c1_folder_without_metadata_and_bare_files(tmp_path, drive_bag):
    folder = tmp_path / 'no_meta'
    shutil.copytree(drive_bag, folder)
    (folder / 'metadata.yaml').unlink()
    with open_recording(folder) as bag:
        assert len(bag.read_wheels()) == 50
        assert any('no metadata.yaml' in n and 'reading 1 storage file' in n for n in bag.notes)
    with open_recording(_storage_file(folder)) as bag:
        assert len(list(bag.iter_lidar())) == 5
        assert any('directly' in n for n in bag.notes)
    empty = tmp_path / 'empty'
    empty.mkdir()
    (empty / 'readme.txt').write_text('x')
    with pytest.raises(RecordingError, match=r'no metadata.yaml and no .db3 / .mcap.*readme'):
        open_recording(empty)


def test_c1_split_files_without_metadata_read_in_time_order(tmp_path):
    folder = tmp_path / 'split'
    folder.mkdir()
    for name, start_ns in (('b_later.db3', T0_NS + 10**9), ('a_earlier.db3', T0_NS)):
        with BagWriter(tmp_path / name) as bag:
            for i in range(3):
                bag.write_joint_state('/js', start_ns + i * 10 * MS, ['left', 'right'],
                                      [1.0, 1.0])
        shutil.copy(_storage_file(tmp_path / name), folder / name)
    with open_recording(folder) as bag:
        wheels = bag.read_wheels()
        assert any('reading 2 storage file(s)' in n for n in bag.notes)
    assert len(wheels) == 6 and wheels.t_ns[0] == T0_NS and wheels.t_ns[-1] > T0_NS + 10**9


# -- C2, C3 --------------------------------------------------------------------------------------
def test_c2_truncated_mcap(tmp_path):
    path = _drive_bag(tmp_path / 'bag', 'mcap')
    mcap = _storage_file(path)
    mcap.write_bytes(mcap.read_bytes()[:mcap.stat().st_size // 2])
    with pytest.raises(RecordingError) as info:
        open_recording(path)
    message = str(info.value)
    assert str(mcap) in message and 'mcap recover' in message and 'reindex' in message


def test_c3_truncated_sqlite(tmp_path):
    path = _drive_bag(tmp_path / 'bag', 'sqlite3')
    db3 = _storage_file(path)
    db3.write_bytes(db3.read_bytes()[:db3.stat().st_size // 2])
    with pytest.raises(RecordingError) as info:
        open_recording(path)
    assert str(db3) in str(info.value) and 'malformed' in str(info.value)


# -- C4 ------------------------------------------------------------------------------------------
def _corrupt_one_overflow_page(db3):
    """Break the overflow chain of one big (multi-page) cloud in the middle of the file."""
    data = bytearray(db3.read_bytes())
    page_size = int.from_bytes(data[16:18], 'big')
    n_pages = len(data) // page_size
    # Overflow pages start with the 4-byte number of the next one; b-tree pages with a type byte.
    chained = [p for p in range(1, n_pages)
               if data[p * page_size] == 0 and
               0 < int.from_bytes(data[p * page_size:p * page_size + 4], 'big') <= n_pages]
    page = chained[len(chained) // 2]
    data[page * page_size:page * page_size + 4] = (n_pages + 1000).to_bytes(4, 'big')
    db3.write_bytes(bytes(data))


def test_c4_storage_error_mid_iteration_skipped_then_fatal(tmp_path):
    path = _drive_bag(tmp_path / 'bag', 'sqlite3', n=100, clouds=10, cloud_points=1000)
    _corrupt_one_overflow_page(_storage_file(path))
    with open_recording(path) as bag:
        assert len(bag.read_wheels()) == 100  # small rows: untouched
        frames = list(bag.iter_lidar())
        assert len(frames) == 9
        assert bag.counts[('/points', 'storage error')] == 1
        assert any('/points' in n and '1 storage error' in n for n in bag.notes)
    with open_recording(path, max_corrupt=0) as bag:
        with pytest.raises(RecordingError, match='damaged'):
            list(bag.iter_lidar())


def test_c4_undecodable_messages_skipped_then_fatal(tmp_path):
    typestore = get_typestore(Stores.ROS2_JAZZY)
    with BagWriter(tmp_path / 'bag') as bag:
        for i in range(20):
            t = T0_NS + i * 10 * MS
            if i in (4, 9, 14):
                msg = typestore.types['sensor_msgs/msg/JointState'](
                    header=typestore.types['std_msgs/msg/Header'](
                        stamp=typestore.types['builtin_interfaces/msg/Time'](sec=0, nanosec=0),
                        frame_id=''),
                    name=['left', 'right'], position=np.zeros(0), velocity=np.ones(2),
                    effort=np.zeros(0))
                raw = typestore.serialize_cdr(msg, msg.__msgtype__)
                bag.write_raw('/joint_states', 'sensor_msgs/msg/JointState', t, raw[:14])
            else:
                bag.write_joint_state('/joint_states', t, ['left', 'right'], [1.0, 1.0])
    with open_recording(tmp_path / 'bag', max_corrupt=3) as bag:
        assert len(bag.read_wheels()) == 17
        assert bag.counts[('/joint_states', 'undecodable message')] == 3
    with open_recording(tmp_path / 'bag', max_corrupt=2) as bag:
        with pytest.raises(RecordingError, match='more than 2 corrupt messages'):
            bag.read_wheels()


# -- C5 ------------------------------------------------------------------------------------------
def test_c5_bad_values_dropped_and_counted(tmp_path):
    speeds = {3: [math.nan, 1.0], 5: [1.0, 1e6], 7: [math.inf, 1.0]}
    stamps = {10: T0_NS + 10**15, 12: T0_NS + 50 * MS, 14: T0_NS + 13 * 10 * MS}
    with BagWriter(tmp_path / 'bag') as bag:
        for i in range(20):
            t = T0_NS + i * 10 * MS
            bag.write_joint_state('/joint_states', t, ['left', 'right'],
                                  speeds.get(i, [1.0, 2.0]), stamp_ns=stamps.get(i, t))
    with open_recording(tmp_path / 'bag') as bag:
        wheels = bag.read_wheels(max_wheel_speed_rad_s=50.0)
        counts = dict(bag.counts)
        notes = list(bag.notes)
    # 3 bad speeds; a stamp a week ahead, one going back, one repeated: 3 out of order.
    assert len(wheels) == 14
    assert np.all(np.diff(wheels.t_ns) > 0) and np.all(np.isfinite(wheels.omega_l))
    assert counts[('/joint_states', 'non-finite speed')] == 2
    assert counts[('/joint_states', 'speed beyond 50 rad/s')] == 1
    assert counts[('/joint_states', 'stamp out of order or repeated')] == 3
    assert any('kept 14 messages' in n and '2 non-finite speed' in n for n in notes)


def test_c5_all_zero_stamps_fall_back_to_receive_time(tmp_path):
    with BagWriter(tmp_path / 'bag') as bag:
        for i in range(4):
            bag.write_joint_state('/js', T0_NS + i * MS, ['left', 'right'], [1.0, 1.0],
                                  stamp_ns=0)
    with open_recording(tmp_path / 'bag') as bag:
        wheels = bag.read_wheels()
        assert any('every header.stamp is zero' in n for n in bag.notes)
    np.testing.assert_array_equal(wheels.t_ns, T0_NS + np.arange(4) * MS)


def test_c5_keep_monotonic_drops_only_the_outliers():
    t = np.array([0, 10, 20, 10**12, 30, 40, 25, 50, 50, 60])
    np.testing.assert_array_equal(t[keep_monotonic(t)], [0, 10, 20, 30, 40, 50, 60])


def test_c5_lidar_stamp_jump_dropped(tmp_path):
    with BagWriter(tmp_path / 'bag') as bag:
        for i in range(6):
            t = T0_NS + i * 100 * MS
            stamp = t + 3600 * 10**9 if i == 2 else t
            bag.write_pointcloud('/points', t, 'lidar', np.ones((4, 3)), stamp_ns=stamp)
    with open_recording(tmp_path / 'bag') as bag:
        frames = list(bag.iter_lidar())
        assert [f.stamp_ns for f in frames] == [T0_NS + i * 100 * MS for i in (0, 1, 3, 4, 5)]
        assert frames[0].t_rel_s is None and frames[0].end_ns == frames[0].stamp_ns
        assert bag.counts[('/points', 'stamp far from receive time')] == 1


# -- C6 ------------------------------------------------------------------------------------------
TICKS_MSG = 'float64 left\nfloat64 right\n'


def _ticks_bytes():
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg(TICKS_MSG, 'acme_msgs/msg/WheelTicks'))
    msg = store.types['acme_msgs/msg/WheelTicks'](left=1.5, right=2.5)
    return store.serialize_cdr(msg, 'acme_msgs/msg/WheelTicks')


def test_c6_unknown_type_needs_its_msg_file(tmp_path):
    with BagWriter(tmp_path / 'bag') as bag:
        bag.write_raw('/ticks', 'acme_msgs/msg/WheelTicks', T0_NS, _ticks_bytes(), msgdef='')
    with open_recording(tmp_path / 'bag') as bag:
        with pytest.raises(RecordingError) as info:
            list(bag.messages('/ticks'))
    message = str(info.value)
    assert '/ticks' in message and 'acme_msgs/msg/WheelTicks' in message and '.msg' in message

    msg_file = tmp_path / 'acme_msgs' / 'msg' / 'WheelTicks.msg'
    msg_file.parent.mkdir(parents=True)
    msg_file.write_text(TICKS_MSG)
    with open_recording(tmp_path / 'bag', msg_files=[msg_file]) as bag:
        [(_, msg)] = list(bag.messages('/ticks'))
    assert (msg.left, msg.right) == (1.5, 2.5)


def test_c6_definition_stored_in_the_bag_is_used(tmp_path):
    with BagWriter(tmp_path / 'bag') as bag:
        bag.write_raw('/ticks', 'acme_msgs/msg/WheelTicks', T0_NS, _ticks_bytes(),
                      msgdef=TICKS_MSG)
    with open_recording(tmp_path / 'bag') as bag:
        [(_, msg)] = list(bag.messages('/ticks'))
    assert msg.right == 2.5


# -- C7 ------------------------------------------------------------------------------------------
def test_c7_topic_absent_wrong_type_empty_or_ambiguous(tmp_path):
    with BagWriter(tmp_path / 'bag') as bag:
        bag.connection('/points', POINTCLOUD2)  # declared, never published
        bag.write_imu('/imu_a', T0_NS, 'imu', [0, 0, 0], [0, 0, 0])
        bag.write_imu('/imu_b', T0_NS, 'imu', [0, 0, 0], [0, 0, 0])
    with open_recording(tmp_path / 'bag') as bag:
        listing = '/imu_a [sensor_msgs/msg/Imu, 1 msgs]'
        with pytest.raises(RecordingError, match='topic /nope is not in') as info:
            bag.read_wheels('/nope')
        assert listing in str(info.value)
        with pytest.raises(RecordingError, match='has type sensor_msgs/msg/Imu, expected') as info:
            bag.iter_lidar('/imu_a')
        assert listing in str(info.value)
        with pytest.raises(RecordingError, match='/points has no messages'):
            bag.iter_lidar()
        with pytest.raises(RecordingError, match=r'several sensor_msgs/msg/Imu topics \(/imu_a'):
            bag.read_imu()
        with pytest.raises(RecordingError, match='no sensor_msgs/msg/JointState topic') as info:
            bag.read_wheels()
        assert listing in str(info.value)
        assert bag.read_imu('/imu_b').t_ns.size == 1


# -- C8 ------------------------------------------------------------------------------------------
def test_c8_overlap_refused_or_returned():
    s = 10**9
    assert check_overlap((0, 100 * s), (20 * s, 90 * s)) == (20 * s, 90 * s)
    with pytest.raises(DataError, match=r'overlap for 5.0 s.*at least 10.0 s') as info:
        check_overlap((0, 100 * s), (95 * s, 200 * s))
    assert '0.000 s .. 100.000 s' in str(info.value) and 'lidar' in str(info.value)
    with pytest.raises(DataError, match='0 %'):
        check_overlap((0, 100 * s), (200 * s, 300 * s))
    with pytest.raises(DataError, match='20 % of the shorter'):
        check_overlap((0, 100 * s), (80 * s, 180 * s), min_seconds=1.0)


# -- C19 -----------------------------------------------------------------------------------------
@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_c19_streaming_memory_stays_far_below_the_bag_size(tmp_path, storage):
    path = tmp_path / 'big'
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-50, 50, (8000, 3))
    with BagWriter(path, storage=storage) as bag:
        for i in range(60):
            bag.write_pointcloud('/points', T0_NS + i * 100 * MS, 'lidar', xyz,
                                 t_point=np.linspace(0, 0.1, 8000))
    bag_bytes = _storage_file(path).stat().st_size
    assert bag_bytes > 60 * 8000 * 16

    def peak_bytes(n_frames):
        with open_recording(path) as bag:
            frames = bag.iter_lidar()
            next(frames)  # warm up caches and imports before measuring
            tracemalloc.start()
            count = 1 + sum(1 for _, __ in zip(range(n_frames - 1), frames))
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
        assert count == n_frames
        return peak

    peak_few, peak_all = peak_bytes(10), peak_bytes(60)
    # Loading the bag would cost at least its size; streaming costs about one frame (or one
    # mcap chunk), whatever the number of frames read.
    assert peak_all < bag_bytes / 2, f'peak {peak_all} B while streaming a {bag_bytes} B bag'
    assert peak_all < 1.5 * peak_few + 200_000, f'{peak_few} B for 10 frames, {peak_all} for 60'


def test_c27_unreadable_metadata_is_not_blamed_on_the_storage_file(tmp_path):
    """Red-team case: a broken metadata.yaml got the remedy `sqlite3 .recover` on the .db3."""
    bag = _drive_bag(tmp_path / 'bag', n=20, clouds=2)
    for text in ('rosbag2_bagfile_information: [', 'foo: 1\n', ''):
        (bag / 'metadata.yaml').write_text(text)
        with open_recording(bag) as rec:
            assert len(rec.read_wheels()) == 20
            note = ' '.join(rec.notes)
        assert 'metadata.yaml cannot be read' in note and 'ros2 bag reindex' in note
        assert 'sqlite3' not in note and '.recover' not in note
    (bag / 'metadata.yaml').write_text('foo: 1\n')
    _storage_file(bag).write_bytes(b'not a database at all' * 100)
    with pytest.raises(RecordingError, match='metadata.yaml cannot be read.*failed too'):
        open_recording(bag)


def test_c28_a_device_or_pipe_as_a_recording_is_refused(tmp_path):
    """Red-team case: /dev/zero as a source ended in a NotADirectoryError traceback."""
    with pytest.raises(RecordingError, match='neither a file nor a folder'):
        open_recording('/dev/zero')
    fifo = tmp_path / 'pipe'
    os.mkfifo(fifo)
    with pytest.raises(RecordingError, match='neither a file nor a folder'):
        open_recording(fifo)


def test_c29_a_topic_whose_messages_were_removed_says_so(tmp_path):
    """Red-team case: a removed JointState topic was reported as 'joints seen: []'."""
    bag = _drive_bag(tmp_path / 'bag', n=20, clouds=2)
    with sqlite3.connect(_storage_file(bag)) as db:
        for topic in ('/joint_states', '/imu'):
            db.execute('DELETE FROM messages WHERE topic_id = '
                       '(SELECT id FROM topics WHERE name = ?)', (topic,))
    with open_recording(bag) as rec:
        with pytest.raises(RecordingError) as err:
            rec.read_wheels()
        assert 'no message on /joint_states could be read, though the recording lists 20' in str(
            err.value)
        assert 'joints seen' not in str(err.value)
        with pytest.raises(RecordingError, match='no message on /imu could be read'):
            rec.read_imu()


def test_c30_wheel_speed_jumps_are_dropped_naming_the_side(tmp_path):
    """Red-team case: 90 rad/s spikes under max_wheel_speed reached the fit and lidar check."""
    spikes = {20: (2.0, 90.0), 40: (-85.0, 2.0), 60: (2.0, 95.0)}
    with BagWriter(tmp_path / 'bag') as bag:
        for i in range(100):
            t = T0_NS + i * 50 * MS
            bag.write_joint_state('/joint_states', t, ['left', 'right'],
                                  list(spikes.get(i, (2.0, 2.0))), stamp_ns=t)
    with open_recording(tmp_path / 'bag') as rec:
        wheels = rec.read_wheels()
        note = next(n for n in rec.notes if 'jumped' in n)
    assert len(wheels) == 97 and np.abs(wheels.omega_l).max() == np.abs(wheels.omega_r).max() == 2
    assert 'dropped 3 of 100 samples of /joint_states' in note
    assert '1 on the left wheel, 2 on the right wheel' in note and 'not the lidar' in note
    with open_recording(tmp_path / 'bag') as rec:  # the node's parameter decides
        assert len(rec.read_wheels(max_wheel_acceleration=1e6)) == 100
