"""BagWriter: every typed writer round-trips through rosbags' own reader, in both storages."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rosbags.interfaces import QosDurability
from rosbags.rosbag2 import Reader
from rosbags.typesys import get_typestore, Stores

from skidkin_ros.adapters.bag_writer import BagWriter
from skidkin_ros.adapters.pointcloud import read_fields
from skidkin_ros.errors import OutputError, RecordingError

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


def _read_all(path):
    with Reader(path) as reader:
        conns = {c.topic: c for c in reader.connections}
        msgs = [(c.topic, t, TYPESTORE.deserialize_cdr(raw, c.msgtype))
                for c, t, raw in reader.messages()]
    return conns, msgs


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_every_writer_round_trips(tmp_path, storage):
    path = tmp_path / 'bag'
    xyz = np.array([[1.0, 2.0, 3.0], [-1.5, 0.25, 0.0]])
    with BagWriter(path, storage=storage) as bag:
        bag.write_tf_static(5, 'base_link', 'lidar', [0.2, 0.0, 0.4], [0.0, 0.0, 0.0, 1.0])
        bag.write_joint_state('/joint_states', 1_000_000_007, ['wl', 'wr'], [1.5, -2.0],
                              positions=[0.1, 0.2], stamp_ns=999_999_999)
        bag.write_float64('/left', 1_000_000_010, 3.25)
        bag.write_pointcloud('/points', 1_000_000_020, 'lidar', xyz,
                             t_point=np.array([0, 50_000_000]), time_dtype='uint32',
                             extra_fields={'intensity': np.array([7.0, 8.0], np.float32)})
        bag.write_imu('/imu', 1_000_000_030, 'imu', [0.0, 0.0, 0.5], [1.0, -1.0, 9.8])
        bag.write_odometry('/odom', 1_000_000_040, 'odom', 'base_link', 1.0, 2.0, 0.5)
        bag.write_pose_stamped('/pose', 1_000_000_050, 'map', -1.0, 3.0, -2.0)
    suffix = '.db3' if storage == 'sqlite3' else '.mcap'
    assert (path / 'metadata.yaml').is_file()
    assert [p.suffix for p in path.iterdir() if p.name != 'metadata.yaml'] == [suffix]

    conns, msgs = _read_all(path)
    by_topic = {topic: (t, msg) for topic, t, msg in msgs}
    assert conns['/tf_static'].ext.offered_qos_profiles[0].durability == \
        QosDurability.TRANSIENT_LOCAL

    t, js = by_topic['/joint_states']
    assert t == 1_000_000_007
    assert (js.header.stamp.sec, js.header.stamp.nanosec) == (0, 999_999_999)
    assert js.name == ['wl', 'wr']
    np.testing.assert_allclose(js.velocity, [1.5, -2.0])
    np.testing.assert_allclose(js.position, [0.1, 0.2])

    assert by_topic['/left'][1].data == 3.25

    cloud = by_topic['/points'][1]
    assert cloud.header.frame_id == 'lidar' and cloud.width == 2
    points = read_fields(cloud)
    assert points.dtype['t'] == np.dtype('<u4')
    np.testing.assert_allclose(points['x'], xyz[:, 0])
    np.testing.assert_array_equal(points['t'], [0, 50_000_000])
    np.testing.assert_allclose(points['intensity'], [7.0, 8.0])

    imu = by_topic['/imu'][1]
    assert imu.angular_velocity.z == 0.5 and imu.linear_acceleration.y == -1.0

    tf = by_topic['/tf_static'][1].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ('base_link', 'lidar')
    assert tf.transform.translation.z == 0.4

    odom = by_topic['/odom'][1]
    q = odom.pose.pose.orientation
    assert odom.child_frame_id == 'base_link' and odom.pose.pose.position.y == 2.0
    assert math.isclose(2.0 * math.atan2(q.z, q.w), 0.5)

    pose = by_topic['/pose'][1]
    q = pose.pose.orientation
    assert pose.header.frame_id == 'map'
    assert math.isclose(2.0 * math.atan2(q.z, q.w), -2.0)


def test_float64_time_dtype_written_as_is(tmp_path):
    t_abs_s = 1.7e9 + np.array([0.0, 0.05, 0.1])
    with BagWriter(tmp_path / 'bag') as bag:
        bag.write_pointcloud('/points', 10, 'lidar', np.zeros((3, 3)), t_point=t_abs_s,
                             time_field='timestamp', time_dtype='float64')
    _, msgs = _read_all(tmp_path / 'bag')
    points = read_fields(msgs[0][2])
    assert points.dtype['timestamp'] == np.dtype('<f8')
    np.testing.assert_array_equal(points['timestamp'], t_abs_s)


def test_existing_path_refused_unless_overwrite(tmp_path):
    path = tmp_path / 'bag'
    with BagWriter(path) as bag:
        bag.write_float64('/a', 1, 1.0)
    with pytest.raises(OutputError, match='already exists'):
        with BagWriter(path):
            pass
    with BagWriter(path, overwrite=True) as bag:
        bag.write_float64('/b', 2, 2.0)
    conns, _ = _read_all(path)
    assert list(conns) == ['/b']


def test_overwrite_refuses_a_folder_that_is_not_a_bag(tmp_path):
    (tmp_path / 'notes.txt').write_text('keep me')
    with pytest.raises(OutputError, match='not part of a rosbag2'):
        BagWriter(tmp_path, overwrite=True).open()
    assert (tmp_path / 'notes.txt').exists()


def test_bad_inputs_rejected(tmp_path):
    with BagWriter(tmp_path / 'bag') as bag:
        with pytest.raises(RecordingError, match='integer nanoseconds'):
            bag.write_float64('/a', 1.5, 1.0)
        with pytest.raises(RecordingError, match='2 names but 1 velocities'):
            bag.write_joint_state('/js', 1, ['a', 'b'], [1.0])
        with pytest.raises(RecordingError, match=r'shape \(N, 3\)'):
            bag.write_pointcloud('/points', 1, 'lidar', np.zeros((4, 2)))
        bag.write_float64('/a', 1, 1.0)
        with pytest.raises(RecordingError, match='already carries std_msgs/msg/Float64'):
            bag.write_imu('/a', 2, 'imu', [0, 0, 0], [0, 0, 0])
    with pytest.raises(RecordingError, match='unknown bag storage'):
        BagWriter(tmp_path / 'x', storage='rosbag1')


def test_bag_closed_cleanly_after_an_error(tmp_path):
    path = tmp_path / 'bag'
    with pytest.raises(RuntimeError):
        with BagWriter(path) as bag:
            bag.write_float64('/a', 1, 1.0)
            raise RuntimeError('simulator crashed')
    _, msgs = _read_all(path)
    assert [m[2].data for m in msgs] == [1.0]
