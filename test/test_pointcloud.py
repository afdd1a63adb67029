"""PointCloud2 decoding and the per-point time rule, on clouds written by BagWriter."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import get_typestore, Stores

from skidkin_ros.adapters.bag_writer import BagWriter
from skidkin_ros.adapters.pointcloud import (find_time_field, interpret_point_times, read_fields,
                                             read_xyz_and_times)
from skidkin_ros.errors import RecordingError

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
STAMP_NS = 1_700_000_000_123_456_789
SWEEP_S = 0.1


def _cloud(tmp_path, xyz, **kwargs):
    path = tmp_path / 'bag'
    with BagWriter(path) as bag:
        bag.write_pointcloud('/points', STAMP_NS, 'lidar', xyz, **kwargs)
    with Reader(path) as reader:
        conn, _, raw = next(iter(reader.messages()))
        return TYPESTORE.deserialize_cdr(raw, conn.msgtype)


def _xyz(n=50):
    rng = np.random.default_rng(3)
    return rng.uniform(-20, 20, (n, 3)).astype(np.float32).astype(np.float64)


def _decode(msg):
    xyz, raw, is_integer, name = read_xyz_and_times(msg)
    return xyz, interpret_point_times(raw, is_integer, STAMP_NS), name


REL_S = np.linspace(0.0, SWEEP_S, 50)


@pytest.mark.parametrize('field, values, dtype, absolute, unit', [
    ('t', (REL_S * 1e9).astype(np.uint32), 'uint32', False, 'ns'),          # Ouster
    ('offset_time', (REL_S * 1e9).astype(np.uint32), 'uint32', False, 'ns'),  # Livox
    ('time', REL_S, 'float32', False, 's'),                                  # Velodyne
    ('time', REL_S - SWEEP_S, 'float32', False, 's'),                        # stamp at sweep end
    ('t', REL_S * 1e3, 'float64', False, 'ms'),
    ('timestamp', STAMP_NS * 1e-9 + REL_S, 'float64', True, 's'),            # Hesai, Robosense
])
def test_time_field_of_any_dtype(tmp_path, field, values, dtype, absolute, unit):
    xyz = _xyz()
    msg = _cloud(tmp_path, xyz, t_point=values, time_field=field, time_dtype=dtype)
    got_xyz, times, name = _decode(msg)
    assert name == field
    np.testing.assert_allclose(got_xyz, xyz)
    assert times is not None and times.absolute == absolute and times.unit == unit
    # Relative to the earliest point, in seconds, whatever the encoding.
    np.testing.assert_allclose(times.t_rel_s, REL_S, atol=2e-6)
    offset_ns = -SWEEP_S * 1e9 if np.min(values) < 0 else 0
    expected_end_ns = STAMP_NS + SWEEP_S * 1e9 + offset_ns
    assert abs(times.end_ns - expected_end_ns) < 5_000  # ns: float32/float64 rounding


def test_small_stamps_keep_relative_times_relative():
    # Sim time: header.stamp 0.5 s, relative float times 0..0.1 s are not absolute.
    times = interpret_point_times(REL_S, False, 500_000_000)
    assert not times.absolute
    assert times.end_ns == 600_000_000
    # ... while absolute times near that small stamp are.
    times = interpret_point_times(0.5 + REL_S, False, 500_000_000)
    assert times.absolute and times.end_ns == 600_000_000


def test_integer_absolute_ns():
    # No standard PointField holds uint64, but a custom driver may send int64-like ns as float64.
    raw = (STAMP_NS + REL_S * 1e9).astype(np.float64)
    times = interpret_point_times(raw, True, STAMP_NS)
    assert times.absolute and times.unit == 'ns'
    assert abs(times.end_ns - (STAMP_NS + SWEEP_S * 1e9)) < 1_000


def test_unusable_times_and_nan_points(tmp_path):
    xyz = _xyz()
    xyz[[3, 7]] = np.nan
    t_ns = (REL_S * 1e9).astype(np.uint32)
    t_ns[:] = 4_000_000_000  # integer times of 4 s: no unit makes that a sweep
    msg = _cloud(tmp_path, xyz, t_point=t_ns, time_dtype='uint32')
    got_xyz, raw, is_integer, _ = read_xyz_and_times(msg)
    assert got_xyz.shape == (48, 3) and np.all(np.isfinite(got_xyz))
    assert raw.shape == (48,) and is_integer
    assert interpret_point_times(raw, is_integer, STAMP_NS) is None
    assert interpret_point_times(np.full(4, np.nan), False, STAMP_NS) is None


def test_nan_times_stay_nan_for_the_icp_stage():
    raw = REL_S.copy()
    raw[5] = np.nan
    times = interpret_point_times(raw, False, STAMP_NS)
    assert np.isnan(times.t_rel_s[5]) and np.nanmax(times.t_rel_s) == pytest.approx(SWEEP_S)


def test_no_time_field_and_extra_fields(tmp_path):
    msg = _cloud(tmp_path, _xyz(5), extra_fields={'intensity': np.arange(5, dtype=np.uint16)})
    xyz, raw, _, name = read_xyz_and_times(msg)
    assert raw is None and name is None and xyz.shape == (5, 3)
    np.testing.assert_array_equal(read_fields(msg)['intensity'], np.arange(5))
    assert find_time_field(['x', 'y', 'z', 'Timestamp']) == 'Timestamp'
    with pytest.raises(RecordingError, match="no time field 'stamp'"):
        read_xyz_and_times(msg, time_field='stamp')


def test_organized_padded_big_endian_cloud():
    """A 2 x 3 organized cloud with row padding and big-endian floats, as some drivers send."""

    class Field:

        def __init__(self, name, offset, datatype):
            self.name, self.offset, self.datatype, self.count = name, offset, datatype, 1

    class Msg:
        pass

    points = np.zeros((2, 3), dtype=np.dtype({'names': ['x', 'y', 'z', 't'],
                                              'formats': ['>f4', '>f4', '>f4', '>u4'],
                                              'offsets': [0, 4, 8, 16], 'itemsize': 20}))
    points['x'] = np.arange(6).reshape(2, 3)
    points['y'] = np.nan  # organized clouds mark missing returns with NaN: row 1 below
    points['y'][0] = 1.0
    points['t'] = np.arange(6).reshape(2, 3) * 10_000_000
    row_step = 3 * 20 + 4
    data = bytearray(2 * row_step)
    for row in range(2):
        data[row * row_step:row * row_step + 60] = points[row].tobytes()
    msg = Msg()
    msg.fields = [Field('x', 0, 7), Field('y', 4, 7), Field('z', 8, 7), Field('t', 16, 6)]
    msg.point_step, msg.row_step, msg.width, msg.height = 20, row_step, 3, 2
    msg.is_bigendian, msg.data = True, np.frombuffer(bytes(data), np.uint8)
    xyz, raw, is_integer, _ = read_xyz_and_times(msg)
    np.testing.assert_array_equal(xyz[:, 0], [0, 1, 2])
    np.testing.assert_array_equal(raw, [0, 1e7, 2e7])
    msg.data = msg.data[:50]
    with pytest.raises(RecordingError, match='too short'):
        read_fields(msg)
