"""Trajectory table reader: layout, held ground truth, metadata and clear errors."""

import math
from pathlib import Path

import numpy as np
import pytest

from skidkin_ros.adapters.table import read_table
from skidkin_ros.errors import RecordingError

HUSKY = Path(__file__).resolve().parents[1] / 'data' / 'husky' / 'drive_husky_windows.csv'

HEADER = 'segment,calib_step,t,cmd_left,cmd_right,wheel_left,wheel_right,x,y,yaw,imu_yaw_rate'


def _write(path, lines):
    path.write_text('\n'.join(lines) + '\n', encoding='utf-8')
    return path


def _rows(segment, step, n=6):
    rows = []
    for i in range(n):
        held = i // 2  # truth refreshed every second row, as in the Husky table
        rows.append(f'{segment},{step},{i * 0.05:.2f},1,2,1.0,{2.0 + i},{held * 0.1},'
                    f'{held * 0.01},{held * 0.02},0.5')
    return rows


def test_segments_become_drives_with_fresh_truth_and_meta(tmp_path):
    path = _write(tmp_path / 'drive.csv', [HEADER] + _rows(7, 2) + _rows(8, 3))
    drives = read_table(path)
    assert [d.meta['segment'] for d in drives] == [7, 8]
    assert [d.meta['calib_step'] for d in drives] == [2, 3]
    first = drives[0]
    assert len(first.wheels) == 6
    np.testing.assert_allclose(first.wheels.omega_r, [2, 3, 4, 5, 6, 7])
    # only the rows where the pose was refreshed are kept as ground truth
    assert len(first.truth) == 3
    np.testing.assert_array_equal(first.truth.t_ns, [0, 100_000_000, 200_000_000])
    np.testing.assert_allclose(first.truth.x, [0.0, 0.1, 0.2])
    assert first.meta['held_truth_rows_dropped'] == 3
    assert first.meta['cmd_left'] == 1
    np.testing.assert_allclose(first.imu.yaw_rate, 0.5)


def test_keep_held_rows_when_asked(tmp_path):
    path = _write(tmp_path / 'drive.csv', [HEADER] + _rows(0, 0))
    assert len(read_table(path, dedupe_held_truth=False)[0].truth) == 6


def test_without_segment_column_one_drive(tmp_path):
    lines = ['t,wheel_left,wheel_right,x,y,yaw,other'] + [
        f'{i * 0.1},1,1,{i * 0.01},0,0,zzz' for i in range(5)]
    drives = read_table(_write(tmp_path / 'plain.csv', lines))
    assert len(drives) == 1 and len(drives[0].truth) == 5


def test_missing_file(tmp_path):
    with pytest.raises(RecordingError, match='does not exist'):
        read_table(tmp_path / 'nope.csv')


def test_missing_columns_listed(tmp_path):
    path = _write(tmp_path / 'bad.csv', ['t,wheel_left,x,y', '0,1,0,0'])
    with pytest.raises(RecordingError) as info:
        read_table(path)
    text = str(info.value)
    assert 'wheel_right' in text and 'yaw' in text and 'it has t, wheel_left, x, y' in text


@pytest.mark.parametrize('value,match', [('abc', 'not a number'), ('nan', 'not finite'),
                                         ('inf', 'not finite')])
def test_bad_values_name_line_and_column(tmp_path, value, match):
    lines = [HEADER] + _rows(0, 0)
    fields = lines[3].split(',')
    fields[7] = value  # x of the third data row
    lines[3] = ','.join(fields)
    with pytest.raises(RecordingError, match=match) as info:
        read_table(_write(tmp_path / 'bad.csv', lines))
    assert "line 4, column 'x'" in str(info.value)


def test_time_must_increase_within_a_segment(tmp_path):
    lines = [HEADER] + _rows(0, 0)
    lines[4], lines[5] = lines[5], lines[4]
    with pytest.raises(RecordingError, match='must increase within segment 0'):
        read_table(_write(tmp_path / 'order.csv', lines))


@pytest.mark.skipif(not HUSKY.is_file(), reason='Husky table not available')
def test_real_husky_layout_is_read():
    drives = read_table(HUSKY)
    assert len(drives) == 603
    assert all(len(d.wheels) == 40 for d in drives)
    assert all(math.isfinite(d.truth.x[-1]) for d in drives)
    assert all(len(d.truth) < 40 for d in drives[:20])


def _with(lines, row, column, value):
    fields = lines[row].split(',')
    fields[HEADER.split(',').index(column)] = value
    lines[row] = ','.join(fields)
    return lines


@pytest.mark.parametrize('t0, needle', [(1.7e12, 'milliseconds since 1970 (divide by 1e3)'),
                                        (1.7e15, 'microseconds since 1970 (divide by 1e6)'),
                                        (1.7e18, 'nanoseconds since 1970 (divide by 1e9)'),
                                        (-1e10, 'cannot be seconds')])
def test_times_that_cannot_be_seconds_say_so(tmp_path, t0, needle):
    """C25: epoch milliseconds gave 't = -9.22e9 s after -9.22e9 s'."""
    lines = [HEADER] + _rows(0, 0)
    for k in range(1, len(lines)):
        _with(lines, k, 't', repr(t0 + k * (1e-3 * t0 if t0 > 0 else 1.0)))
    with pytest.raises(RecordingError, match='cannot be seconds') as info:
        read_table(_write(tmp_path / 'ms.csv', lines))
    assert needle in str(info.value) and "line 2, column 't'" in str(info.value)
    one = _with([HEADER] + _rows(0, 0), 3, 't', '1e10')  # one corrupt time among seconds
    with pytest.raises(RecordingError, match=r"line 4, column 't': t = 1e\+10 cannot be seconds"):
        read_table(_write(tmp_path / 'one.csv', one))
    epoch = [HEADER] + _rows(0, 0)
    for k in range(1, len(epoch)):
        _with(epoch, k, 't', f'{1.7e9 + 0.05 * k:.3f}')  # epoch seconds are seconds
    assert len(read_table(_write(tmp_path / 'epoch.csv', epoch))[0].wheels) == 6


@pytest.mark.parametrize('column, value, match', [
    ('x', '1_0', 'not a number'), ('wheel_left', '١٠', 'not a number'),
    ('y', '0x10', 'not a number'), ('x', '1e300', 'beyond any plausible x'),
    ('wheel_right', '-2e4', 'beyond any plausible wheel_right'),
    ('yaw', '-1e10', 'beyond 4.5e.09 rad'), ('yaw', 'nan', 'not finite'),
    ('t', 'Infinity', 'not finite'),
    # C103: the gyro has its own limit (it was the wheel speeds' 1e4 rad/s)
    ('imu_yaw_rate', '500', "beyond any gyro's range")])
def test_numbers_are_plain_decimals_within_physical_bounds(tmp_path, column, value, match):
    """C26: '1_0' read as 10; a row of 1e300 passed (overflow warnings)."""
    lines = _with([HEADER] + _rows(0, 0), 3, column, value)
    with pytest.raises(RecordingError, match=match) as info:
        read_table(_write(tmp_path / 'bad.csv', lines))
    assert f"line 4, column '{column}'" in str(info.value)


def test_yaw_is_bounded_as_an_angle_float64_resolves_not_in_metres(tmp_path):
    """An unwrapped yaw may grow: refused only where float64 stops resolving 1e-6 rad."""
    # 2e9 rad (3 rad/s for 21 years) is still an angle float64 holds to 2.4e-7 rad: read
    lines = [HEADER] + _rows(0, 0)
    for k in range(1, len(lines)):
        _with(lines, k, 'yaw', f'{2e9 + 0.01 * k:.2f}')
    drive = read_table(_write(tmp_path / 'spun.csv', lines))[0]
    assert np.all(np.abs(drive.truth.poses[:, 2] - 2e9) < 1.0)
    # 5e9 rad: neighbouring floats are 9.5e-7 rad apart; the error says why and what to do
    bad = _with([HEADER] + _rows(0, 0), 3, 'yaw', '5e9')
    with pytest.raises(RecordingError) as info:
        read_table(_write(tmp_path / 'far.csv', bad))
    text = str(info.value)
    assert "line 4, column 'yaw': yaw = 5e+09 rad is beyond 4.5e+09 rad" in text
    assert 'no longer resolves 1e-06 rad' in text and 'angle in radians' in text


def test_a_fast_but_real_gyro_rate_is_read(tmp_path):
    """C103: 300 rad/s is inside the widest gyro range (349 rad/s) and is read."""
    lines = _with([HEADER] + _rows(0, 0), 3, 'imu_yaw_rate', '-300')
    drive = read_table(_write(tmp_path / 'fast.csv', lines))[0]
    assert drive.imu.yaw_rate[2] == -300.0


def test_byte_order_mark_and_repeated_columns(tmp_path):
    """C26: a UTF-8 byte-order mark hid the t column."""
    path = tmp_path / 'bom.csv'
    path.write_bytes(('\ufeff' + '\n'.join([HEADER] + _rows(0, 0)) + '\n').encode('utf-8'))
    drives = read_table(path)
    assert drives[0].wheels.t_ns[1] == 50_000_000
    twice = _write(tmp_path / 'twice.csv', [HEADER + ',x'] + [r + ',9' for r in _rows(0, 0)])
    with pytest.raises(RecordingError, match='column.s. x more than once'):
        read_table(twice)
