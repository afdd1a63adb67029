"""PointCloud2 <-> numpy, and per-point time fields of any numeric type.

The functions here are duck-typed on the message (``fields``, ``point_step``, ``row_step``,
``width``, ``height``, ``is_bigendian``, ``data``), so they work on rosbags' deserialized messages
and on rclpy's alike; they do not import rosbags.

Per-point times: the rule that decides absolute vs relative and the unit
--------------------------------------------------------------------------
Drivers disagree: Ouster writes ``t`` as uint32 ns relative to the sweep start, Livox
``offset_time`` as uint32 ns, Velodyne ``time`` as float32 s relative (sometimes negative, when the
header stamp is the end of the sweep), Hesai / Robosense ``timestamp`` as float64 absolute s, some
drivers uint64 absolute ns. :func:`interpret_point_times` decides from the values themselves:

1. **Absolute** when, in the unit of the dtype (float: s; integer: ns, else us), the median
   time lies within ``ABSOLUTE_TOLERANCE_S`` (1 s) of ``header.stamp`` *and* is closer to
   ``header.stamp`` than to zero (so relative times of a sim-time bag, whose stamps are small,
   stay relative; below a stamp of about one sweep the two cannot be told apart).
2. Otherwise **relative to header.stamp**, with the unit chosen from the dtype: integer fields are
   nanoseconds (every integer driver we know of); float fields take the largest unit among s, ms,
   us, ns for which the largest magnitude fits in a sweep (``MAX_SWEEP_S``, 1 s).
3. If neither fits (e.g. integer times far beyond a second, absolute times far from the stamp),
   the times are reported as unusable (``None``) and the caller keeps the cloud without them.

``t_rel_s`` is then relative to the earliest point, and ``end_ns`` is the absolute time of the
latest point: the time itself for absolute fields, ``header.stamp + max(offset)`` for relative ones
(assumption: relative offsets are measured from ``header.stamp``, as every driver above does).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from skidkin_ros.core.timeunits import s_to_ns
from skidkin_ros.errors import RecordingError

__all__ = [
    'POINTFIELD_DATATYPES',
    'TIME_FIELD_NAMES',
    'ABSOLUTE_TOLERANCE_S',
    'MAX_SWEEP_S',
    'FieldSpec',
    'PointTimes',
    'datatype_of',
    'pack_points',
    'cloud_dtype',
    'read_fields',
    'find_time_field',
    'read_xyz_and_times',
    'interpret_point_times',
    'columns_from_mapping',
]

# sensor_msgs/PointField datatype constants -> numpy type codes (little-endian unless told).
POINTFIELD_DATATYPES: dict[int, str] = {
    1: 'i1', 2: 'u1', 3: 'i2', 4: 'u2', 5: 'i4', 6: 'u4', 7: 'f4', 8: 'f8',
}
_DATATYPE_BY_CODE = {np.dtype(code): datatype for datatype, code in POINTFIELD_DATATYPES.items()}

# Names of per-point time fields, most common first (matched case-insensitively).
TIME_FIELD_NAMES: tuple[str, ...] = (
    't', 'time', 'timestamp', 'offset_time', 'time_offset', 'timeoffset', 'time_stamp', 'ts',
)

ABSOLUTE_TOLERANCE_S = 1.0
MAX_SWEEP_S = 1.0
_UNITS_S: tuple[tuple[str, float], ...] = (('s', 1.0), ('ms', 1e-3), ('us', 1e-6), ('ns', 1e-9))


@dataclass(frozen=True)
class FieldSpec:
    """One sensor_msgs/PointField: name, byte offset, datatype constant, count."""

    name: str
    offset: int
    datatype: int
    count: int = 1


@dataclass(frozen=True)
class PointTimes:
    """Per-point times decoded from a time field (see the module docstring for the rule)."""

    t_rel_s: np.ndarray
    end_ns: int
    absolute: bool
    unit: str


def datatype_of(dtype: Any) -> int:
    """Return the PointField datatype constant of a numpy dtype (int8 ... float64)."""
    key = np.dtype(dtype).newbyteorder('=')
    try:
        return _DATATYPE_BY_CODE[key]
    except KeyError as err:
        raise RecordingError(
            f'point field dtype {np.dtype(dtype)} has no PointField datatype; use one of '
            'int8, uint8, int16, uint16, int32, uint32, float32, float64') from err


def pack_points(columns: Sequence[tuple[str, np.ndarray, Any]]
                ) -> tuple[list[FieldSpec], int, np.ndarray]:
    """Pack named 1-D columns into a little-endian point buffer.

    ``columns`` are ``(name, values (N,), dtype)``; fields are laid out back to back in that order.
    Return the field specs, the point step (bytes) and the data as a flat uint8 array.
    """
    if not columns:
        raise RecordingError('a point cloud needs at least one field (x, y, z)')
    n_points = int(np.asarray(columns[0][1]).shape[0])
    specs: list[FieldSpec] = []
    names: list[str] = []
    formats: list[np.dtype] = []
    offsets: list[int] = []
    offset = 0
    for name, values, dtype in columns:
        values = np.asarray(values)
        if values.shape != (n_points,):
            raise RecordingError(f'point field {name!r}: expected shape ({n_points},), '
                                 f'got {values.shape}')
        code = np.dtype(dtype).newbyteorder('<')
        specs.append(FieldSpec(name, offset, datatype_of(code)))
        names.append(name)
        formats.append(code)
        offsets.append(offset)
        offset += code.itemsize
    dtype = np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                      'itemsize': offset})
    packed = np.zeros(n_points, dtype=dtype)
    for name, values, _ in columns:
        packed[name] = np.asarray(values)
    return specs, offset, packed.view(np.uint8).reshape(-1)


def cloud_dtype(fields: Sequence[Any], point_step: int, is_bigendian: bool) -> np.dtype:
    """Return the structured numpy dtype of one point of a PointCloud2 (padding kept)."""
    order = '>' if is_bigendian else '<'
    names, formats, offsets = [], [], []
    for field in fields:
        code = POINTFIELD_DATATYPES.get(int(field.datatype))
        if code is None:
            # Unknown datatype: skip the field rather than refuse the whole cloud.
            continue
        base = np.dtype(code).newbyteorder(order)
        count = max(int(field.count), 1)
        names.append(field.name)
        formats.append(base if count == 1 else np.dtype((base, (count,))))
        offsets.append(int(field.offset))
    if not names:
        raise RecordingError('point cloud has no readable fields; expected at least x, y, z')
    try:
        return np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                         'itemsize': int(point_step)})
    except ValueError as err:
        raise RecordingError(
            f'point cloud fields {names} do not fit the point step of {point_step} bytes; '
            'the message is malformed') from err


def read_fields(msg: Any) -> np.ndarray:
    """Return the points of a PointCloud2 as a structured array (a view on ``msg.data``)."""
    dtype = cloud_dtype(msg.fields, msg.point_step, bool(msg.is_bigendian))
    width, height = int(msg.width), int(msg.height)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    data = np.frombuffer(memoryview(msg.data), dtype=np.uint8)
    n_points = width * height
    if n_points == 0:
        return np.zeros(0, dtype=dtype)
    if row_step < width * point_step or data.size < row_step * (height - 1) + width * point_step:
        raise RecordingError(
            f'point cloud data of {data.size} bytes is too short for {height} x {width} points of '
            f'{point_step} bytes (row step {row_step}); the message is truncated or malformed')
    if row_step == width * point_step:
        return np.frombuffer(data, dtype=dtype, count=n_points)
    rows = [np.frombuffer(data[r * row_step:r * row_step + width * point_step], dtype=dtype)
            for r in range(height)]
    return np.concatenate(rows)


def find_time_field(names: Sequence[str]) -> str | None:
    """Return the per-point time field among ``names`` (first of TIME_FIELD_NAMES), or None."""
    lowered = {name.lower(): name for name in names}
    for candidate in TIME_FIELD_NAMES:
        if candidate in lowered:
            return lowered[candidate]
    return None


def _column(points: np.ndarray, name: str) -> np.ndarray:
    values = points[name]
    if values.ndim > 1:
        values = values[:, 0]
    return values


def read_xyz_and_times(msg: Any, time_field: str | None = None
                       ) -> tuple[np.ndarray, np.ndarray | None, bool, str | None]:
    """Return xyz (N, 3) float64, raw times (N,) float64 or None, integer-ness, time field name.

    Points with a non-finite coordinate are dropped (organized clouds mark no-return with NaN).
    ``time_field`` None: detect it among TIME_FIELD_NAMES.
    """
    points = read_fields(msg)
    names = points.dtype.names or ()
    missing = [axis for axis in ('x', 'y', 'z') if axis not in names]
    if missing:
        raise RecordingError(f'point cloud has no field(s) {missing}; fields present: '
                             f'{list(names)}; expected x, y, z')
    columns = [_column(points, axis).astype(np.float64) for axis in ('x', 'y', 'z')]
    xyz = np.stack(columns, axis=-1)
    # column by column: numpy's reductions over a row of 3 cost more than the test itself
    keep = np.isfinite(columns[0]) & np.isfinite(columns[1]) & np.isfinite(columns[2])
    every = bool(np.all(keep))
    name = time_field if time_field is not None else find_time_field(names)
    raw = None
    is_integer = False
    if name is not None:
        if name not in names:
            raise RecordingError(f'point cloud has no time field {name!r}; fields present: '
                                 f'{list(names)}')
        column = _column(points, name)
        is_integer = column.dtype.kind in 'iu'
        raw = (column if every else column[keep]).astype(np.float64)
    return (xyz if every else xyz[keep]), raw, is_integer, name


def _absolute_unit(median: float, stamp_s: float, is_integer: bool
                   ) -> tuple[str, float] | None:
    # Absolute times come as float seconds or integer ns / us; nothing else is seen in drivers
    # and allowing it would mistake small relative ms values for absolute times near t=0.
    units = (_UNITS_S[3], _UNITS_S[2]) if is_integer else _UNITS_S[:1]
    for unit, scale in units:
        value_s = median * scale
        gap_s = abs(value_s - stamp_s)
        if gap_s <= ABSOLUTE_TOLERANCE_S and gap_s < abs(value_s):
            return unit, scale
    return None


def _relative_unit(magnitude: float, is_integer: bool) -> tuple[str, float] | None:
    candidates = _UNITS_S[-1:] if is_integer else _UNITS_S
    for unit, scale in candidates:
        if magnitude * scale <= MAX_SWEEP_S:
            return unit, scale
    return None


def interpret_point_times(raw: np.ndarray, is_integer: bool, stamp_ns: int
                          ) -> PointTimes | None:
    """Decode raw per-point times (see the module docstring); None when they fit no rule.

    NaN times stay NaN in ``t_rel_s`` (the ICP stage decides whether to deskew); when every time
    is NaN the result is None.
    """
    raw = np.asarray(raw, dtype=np.float64)
    finite = raw[np.isfinite(raw)]
    if finite.size == 0:
        return None
    stamp_s = stamp_ns * 1e-9
    t_min, t_max = float(finite.min()), float(finite.max())
    absolute = _absolute_unit(float(np.median(finite)), stamp_s, is_integer)
    if absolute is not None:
        unit, scale = absolute
        # Subtract before scaling: absolute float64 seconds lose ns precision otherwise.
        t_rel_s = (raw - t_min) * scale
        end_ns = s_to_ns(t_max * scale) if scale >= 1e-6 else int(t_max)
        return PointTimes(t_rel_s, end_ns, True, unit)
    relative = _relative_unit(max(abs(t_min), abs(t_max)), is_integer)
    if relative is None:
        return None
    unit, scale = relative
    t_rel_s = (raw - t_min) * scale
    end_ns = int(stamp_ns) + s_to_ns(t_max * scale)
    return PointTimes(t_rel_s, end_ns, False, unit)


Column = tuple[str, np.ndarray, Any]


def columns_from_mapping(extra: Mapping[str, np.ndarray] | None) -> list[Column]:
    """Return ``(name, values, dtype)`` columns for extra fields, keeping each array's dtype."""
    if not extra:
        return []
    return [(name, np.asarray(values), np.asarray(values).dtype) for name, values in extra.items()]
