"""Trajectory table reader: layout, held ground truth, metadata and clear errors."""

import math
from pathlib import Path

import numpy as np
import pytest

from skidkin_ros.adapters.table import read_table
from skidkin_ros.errors import RecordingError

HUSKY = Path(__file__).resolve().parents[2] / 'shared' / 'data' / 'drive_husky_windows.csv'

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


def test_real_husky_layout_is_read():
    drives = read_table(HUSKY)
    assert len(drives) == 603
    assert all(len(d.wheels) == 40 for d in drives)
    assert all(math.isfinite(d.truth.x[-1]) for d in drives)
    assert all(len(d.truth) < 40 for d in drives[:20])
