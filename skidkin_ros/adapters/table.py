"""Read a trajectory table (CSV) into drives: wheel speeds plus ground-truth poses.

Columns (header row required, any order, extra columns ignored; UTF-8, a byte-order mark is
skipped):

- ``t`` (s), ``wheel_left``, ``wheel_right`` (rad/s), ``x``, ``y`` (m), ``yaw`` (rad): required;
- ``segment``: optional; rows of one segment are one continuous trajectory in its own frame,
  different segments are independent (each becomes one :class:`Drive`);
- ``calib_step``, ``cmd_left``, ``cmd_right`` are kept in ``Drive.meta``; ``imu_yaw_rate``
  becomes :class:`ImuSamples`.

Values are plain decimal numbers (``1.5``, ``-2e-3``; not ``1_0``, not other scripts' digits)
within physical bounds (:data:`VALUE_LIMITS`: a position of 1e300 m is a corrupt row, and would
overflow every sum it enters; an unwrapped yaw may grow with every turn, so its bound is where
float64 stops resolving 1e-6 rad, about 4.5e9 rad); ``t`` must be seconds: a time beyond the
int64 nanosecond range (about 9.2e9 s) is refused with the unit it looks like (milliseconds
since 1970, ...).

Sample-and-held ground truth. Lidar/ICP poses often come slower than the wheel samples and are
held onto the table's time grid (the DRIVE Husky table: ICP at ~10 Hz held onto 20 Hz rows), so
consecutive rows repeat the same pose. A held pose is stale: using it as a segment end would
compare the model at time t with where the robot was up to one ICP period earlier. With
``dedupe_held_truth=True`` (default) the ground truth keeps only the rows where the pose was
refreshed (the first row of each run of identical (x, y, yaw):
:func:`skidkin_ros.core.drive.fresh_pose_mask`); segments then start and end on
fresh poses only. We do not interpolate between fresh poses: their true stamps are unknown within
one grid period anyway, and interpolation would invent poses the ICP never produced. Wheel speeds
keep every row.
"""

from __future__ import annotations

import csv
import logging
import math
from pathlib import Path
import re
from typing import Sequence

import numpy as np

from skidkin_ros.core.drive import Drive, fresh_pose_mask, ImuSamples, PoseTrack, WheelSamples
from skidkin_ros.core.odometry.gyro_params import GYRO_RATE_LIMIT
from skidkin_ros.core.odometry.pose_limits import POSE_LIMIT_M, YAW_LIMIT_RAD, YAW_RESOLUTION_RAD
from skidkin_ros.core.odometry.schema import NODE_SPECS
from skidkin_ros.core.timeunits import s_to_ns_array
from skidkin_ros.errors import RecordingError

__all__ = ['REQUIRED_COLUMNS', 'META_COLUMNS', 'read_table']

LOG = logging.getLogger(__name__)

REQUIRED_COLUMNS: tuple[str, ...] = ('t', 'wheel_left', 'wheel_right', 'x', 'y', 'yaw')
META_COLUMNS: tuple[str, ...] = ('calib_step', 'cmd_left', 'cmd_right')
OPTIONAL_COLUMNS: tuple[str, ...] = ('segment', 'imu_yaw_rate') + META_COLUMNS

# A plain decimal number, ASCII digits only (float() also takes '1_0' and non-ASCII digits).
_NUMBER = re.compile(r'[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?', re.ASCII)
# Largest time in s that integer nanoseconds hold (int64): about the year 2262 since 1970.
MAX_TIME_S = 9.2e9
_WHEEL_LIMIT = next(spec.upper for spec in NODE_SPECS if spec.name == 'max_wheel_speed')
# Bounds of the values of a column (unit): beyond them a value is a corrupt row.
VALUE_LIMITS: dict[str, tuple[float, str]] = {
    'wheel_left': (_WHEEL_LIMIT, 'rad/s'), 'wheel_right': (_WHEEL_LIMIT, 'rad/s'),
    'cmd_left': (_WHEEL_LIMIT, 'rad/s'), 'cmd_right': (_WHEEL_LIMIT, 'rad/s'),
    'imu_yaw_rate': (GYRO_RATE_LIMIT, 'rad/s'), 'x': (POSE_LIMIT_M, 'm'), 'y': (POSE_LIMIT_M, 'm'),
    'yaw': (YAW_LIMIT_RAD, 'rad'), 't': (MAX_TIME_S, 's')}


def _read_rows(path: Path) -> tuple[list[str], list[list[str]]]:
    if not path.exists():
        raise RecordingError(f'trajectory table {path} does not exist; give the path of a CSV '
                             f'file with columns {", ".join(REQUIRED_COLUMNS)}')
    if not path.is_file():
        raise RecordingError(f'trajectory table {path} is not a file')
    try:
        with path.open(newline='', encoding='utf-8-sig') as handle:
            reader = csv.reader(handle)
            header = next(reader, None)
            rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise RecordingError(f'trajectory table {path} cannot be read as CSV: {err}') from err
    if header is None:
        raise RecordingError(f'trajectory table {path} is empty; expected a header row with '
                             f'{", ".join(REQUIRED_COLUMNS)}')
    names = [name.strip() for name in header]
    repeated = sorted({name for name in names if names.count(name) > 1 and name})
    if repeated:
        raise RecordingError(f'trajectory table {path} has column(s) {", ".join(repeated)} more '
                             'than once; keep one of each (which one is meant is not clear)')
    return names, rows


def _numeric_columns(path: Path, header: list[str], rows: list[list[str]],
                     wanted: Sequence[str]) -> dict[str, np.ndarray]:
    index = {name: header.index(name) for name in wanted}
    values = {name: np.empty(len(rows)) for name in wanted}
    for row_no, row in enumerate(rows):
        line = row_no + 2  # 1-based, after the header
        if len(row) < len(header):
            raise RecordingError(f'{path}: line {line} has {len(row)} fields, the header has '
                                 f'{len(header)}; fix or remove the truncated row')
        for name, col in index.items():
            values[name][row_no] = _number(path, line, name, row[col].strip())
    return values


def _number(path: Path, line: int, name: str, text: str) -> float:
    """Return one cell as a float, or raise RecordingError naming line and column."""
    where = f'{path}: line {line}, column {name!r}'
    if not _NUMBER.fullmatch(text):
        try:
            special = float(text)
        except ValueError:
            special = 0.0
        if not math.isfinite(special):
            raise RecordingError(f'{where}: value {text[:40]!r} is not finite; remove or repair '
                                 'the row')
        raise RecordingError(f'{where}: {text[:40]!r} is not a number (expected a plain decimal '
                             'number such as 1.5 or -2e-3)')
    number = float(text)
    limit, unit = VALUE_LIMITS.get(name, (math.inf, ''))
    if not math.isfinite(number):
        raise RecordingError(f'{where}: value {text[:40]!r} is not finite; remove or repair the '
                             'row')
    if abs(number) > limit:
        if name == 't':
            raise RecordingError(f'{where}: t = {number:.6g} cannot be seconds (beyond '
                                 f'{MAX_TIME_S:.3g} s, the year 2262 since 1970); it looks like '
                                 f'{_time_unit(number)}: convert t to seconds')
        if name == 'yaw':
            raise RecordingError(
                f'{where}: yaw = {number:.6g} rad is beyond {YAW_LIMIT_RAD:.3g} rad (about '
                f'{YAW_LIMIT_RAD / (2 * math.pi):.2g} turns), where float64 no longer resolves '
                f'{YAW_RESOLUTION_RAD:g} rad; yaw is an angle in radians (unwrapped is fine): '
                'check the column and remove or repair the row')
        if name == 'imu_yaw_rate':
            raise RecordingError(f"{where}: value {number:.6g} rad/s is beyond any gyro's "
                                 f'range (|imu_yaw_rate| <= {limit:g} rad/s, about 23 000 '
                                 'deg/s); the column is the gyro yaw rate in rad/s: remove or '
                                 'repair the row')
        raise RecordingError(f'{where}: value {number:.6g} is beyond any plausible {name} '
                             f'(|{name}| <= {limit:g} {unit}); remove or repair the row')
    return number


def _time_unit(t: float) -> str:
    """Name the unit a time stamp far beyond seconds most likely has."""
    for limit, unit in ((1e14, 'milliseconds since 1970 (divide by 1e3)'),
                        (1e17, 'microseconds since 1970 (divide by 1e6)'),
                        (1e20, 'nanoseconds since 1970 (divide by 1e9)')):
        if abs(t) < limit:
            return unit
    return 'a corrupt value'


def _segment_order(segment: np.ndarray) -> list[float]:
    """Segment ids in order of first appearance (a stable, deterministic order)."""
    _, first = np.unique(segment, return_index=True)
    return [float(segment[i]) for i in sorted(first)]


def _check_time(path: Path, t_ns: np.ndarray, rows: np.ndarray, label: str) -> None:
    bad = np.nonzero(np.diff(t_ns) <= 0)[0]
    if bad.size:
        line = int(rows[bad[0] + 1]) + 2
        raise RecordingError(
            f'{path}: time t must increase within {label}; line {line} has t = '
            f'{t_ns[bad[0] + 1] * 1e-9:.9g} s after {t_ns[bad[0]] * 1e-9:.9g} s. Sort the rows '
            'or give each continuous stretch its own "segment" id')


def _meta_value(values: np.ndarray):
    if values.size and np.all(values == values[0]):
        number = float(values[0])
        return int(number) if number.is_integer() else number
    return values.copy()


def read_table(path: str | Path, dedupe_held_truth: bool = True) -> list[Drive]:
    """Read a CSV trajectory table into one :class:`Drive` per segment (see module docstring).

    Raises RecordingError for a missing file, missing columns (listing those present),
    non-numeric or non-finite values (naming line and column) and time not increasing within a
    segment.
    """
    source = Path(path)
    header, rows = _read_rows(source)
    missing = [name for name in REQUIRED_COLUMNS if name not in header]
    if missing:
        raise RecordingError(
            f'trajectory table {source} lacks column(s) {", ".join(missing)}; it has '
            f'{", ".join(header) or "no columns"}. Required: {", ".join(REQUIRED_COLUMNS)} '
            '(t in s, wheel speeds in rad/s, x/y in m, yaw in rad)')
    if not rows:
        raise RecordingError(f'trajectory table {source} has a header but no data rows')
    wanted = list(REQUIRED_COLUMNS) + [name for name in OPTIONAL_COLUMNS if name in header]
    cols = _numeric_columns(source, header, rows, wanted)
    segment = cols.get('segment', np.zeros(len(rows)))
    drives = []
    for seg_id in _segment_order(segment):
        rows_idx = np.nonzero(segment == seg_id)[0]
        label = f'segment {seg_id:g}' if 'segment' in cols else 'the table'
        t_ns = s_to_ns_array(cols['t'][rows_idx])
        _check_time(source, t_ns, rows_idx, label)
        x, y, yaw = (cols[name][rows_idx] for name in ('x', 'y', 'yaw'))
        keep = fresh_pose_mask(x, y, yaw) if dedupe_held_truth else np.ones(x.shape, bool)
        wheels = WheelSamples(t_ns, cols['wheel_left'][rows_idx], cols['wheel_right'][rows_idx])
        truth = PoseTrack(t_ns[keep], x[keep], y[keep], yaw[keep])
        imu = None
        if 'imu_yaw_rate' in cols:
            imu = ImuSamples(t_ns, cols['imu_yaw_rate'][rows_idx])
        meta = {'source': str(source), 'rows': (int(rows_idx[0]) + 2, int(rows_idx[-1]) + 2),
                'row_index': rows_idx,
                'held_truth_rows_dropped': int((~keep).sum())}
        if 'segment' in cols:
            meta['segment'] = _meta_value(np.array([seg_id]))
        for name in META_COLUMNS:
            if name in cols:
                meta[name] = _meta_value(cols[name][rows_idx])
        name = f'{source.stem}#{seg_id:g}' if 'segment' in cols else source.stem
        drives.append(Drive(name, wheels, truth, imu, meta))
    LOG.info('read %d drive(s) from %s (%d rows)', len(drives), source, len(rows))
    return drives
