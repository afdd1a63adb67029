"""The gyro's parameters and vocabulary.

The ``imu.*`` node parameters and their specs, the modes, the sample and interval statuses, and
the limits the gyro's sample rules and the wheels share.

Shared by :mod:`~skidkin_ros.core.odometry.gyro_buffer` (the sample rules),
:mod:`~skidkin_ros.core.odometry.gyro_filter` (the gain/bias filter) and
:mod:`~skidkin_ros.core.odometry.gyro` (the aid), and by the node's configuration.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
import enum
from typing import Any, Mapping

from skidkin_ros.core.kinematics.specs import check_value, ParamSpec

__all__ = ['GYRO_MODES', 'GYRO_SPECS', 'GYRO_RATE_LIMIT', 'STEP_BACK_CONFIRM', 'GyroParams',
           'GyroStatus']

GYRO_MODES = ('off', 'adapt', 'fuse')
# |yaw rate| no gyro measures (rad/s): the widest MEMS ranges are +-20 000 deg/s (349 rad/s).
# A recorded rate beyond it is a corrupt value, not a saturated sample.
GYRO_RATE_LIMIT = 400.0
# Samples in a row that confirm a stepped-back clock (one corrupt stamp is not a restart); the
# wheels' rule (the odometer imports it from here).
STEP_BACK_CONFIRM = 3


# Node parameters imu.<name> (units in the descriptor, not the name; ranges as the node checks).
GYRO_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec('scale', '', 1.0, 0.5, 2.0,
              'gyro yaw-rate scale: g = scale * omega + bias (calibrated; a z-down IMU '
              'would be -1: fix the driver or the frame)'),
    ParamSpec('bias', 'rad/s', 0.0, -1.0, 1.0, 'gyro yaw-rate bias (calibrated)'),
    ParamSpec('time_offset', 's', 0.0, -1.0, 1.0,
              'gyro stamp minus the wheel stamp of the same motion (> 0: gyro stamps late; '
              'calibrated)'),
    ParamSpec('timeout', 's', 0.2, 0.0, 10.0,
              'no usable gyro sample this long before an interval end: gyro stale, the odometry '
              'goes on with the learned gain', lower_open=True),
    ParamSpec('max_gap', 's', 0.08, 0.0, 1.0,
              'longest gap between usable gyro samples inside an interval (a 20 Hz gyro needs '
              '0.06+)', lower_open=True),
    ParamSpec('max_wait', 's', 0.05, 0.0, 0.5,
              'node: longest wait of a wheel sample for the gyro samples that cover it'),
    ParamSpec('saturation', 'rad/s', 35.0, 0.0, 1e4,
              '|rate| at or above this is saturated (or absurd) and not used; set ~0.95 x the '
              'gyro range (default: 2000 deg/s, the largest usual MEMS range)', lower_open=True),
    ParamSpec('spike', 'rad/s', 0.5, 0.0, 1e4,
              'a sample this far from both its neighbours (a peak) is a glitch, skipped',
              lower_open=True),
    ParamSpec('arw', 'rad/sqrt(s)', 2e-3, 0.0, 1.0,
              'gyro white noise (angle random walk): the heading noise of fuse'),
    ParamSpec('bias_sigma', 'rad/s', 1e-3, 0.0, 1.0,
              'prior standard deviation of the residual gyro bias', lower_open=True),
    ParamSpec('q_bias', '(rad/s)^2/s', 1e-8, 0.0, 1.0, 'random walk of the gyro bias'),
    ParamSpec('adapt.q_gain', '1/m', 0.03, 0.0, 10.0,
              'random walk of the yaw-rate gain per metre of wheel travel'),
    ParamSpec('adapt.gain_sigma', '', 0.05, 0.0, 1.0,
              'prior standard deviation of the yaw-rate gain', lower_open=True),
    ParamSpec('adapt.r_floor', '(rad/s)^2', 0.033, 0.0, 100.0,
              'variance of gyro minus model yaw rate per interval, constant part',
              lower_open=True),
    ParamSpec('adapt.r_rel', '', 0.42, 0.0, 10.0,
              'relative part of that standard deviation (times the model yaw rate)'),
    ParamSpec('adapt.huber_k', '', 3.0, 1.0, 100.0,
              'innovations beyond this many sigma count as this many (a glitch cannot drag '
              'the gain)'),
    ParamSpec('adapt.gain_min', '', 0.5, 0.0, 1.0, 'lower bound of the yaw-rate gain',
              lower_open=True, upper_open=True),
    ParamSpec('adapt.gain_max', '', 1.5, 1.0, 100.0, 'upper bound of the yaw-rate gain',
              lower_open=True),
    ParamSpec('adapt.fallback_distance', 'm', 50.0, 0.0, 1e9,
              'gyro stale: the gain relaxes to 1 (the calibrated model) over this wheel travel',
              lower_open=True),
    ParamSpec('adapt.standstill', 'rad/s', 0.02, 0.0, 100.0,
              'both wheels slower than this: standstill (the bias is learned, fuse turns 0)'),
    ParamSpec('adapt.yaw_noise_scale', '', 1.0, 0.0, 100.0,
              "adapt: the model's yaw variance times this (the gyro removes part of the "
              "model's heading error; calibrated)"),
)
_ATTR = {spec.name: spec.name.replace('adapt.', '') for spec in GYRO_SPECS}


@dataclass(frozen=True)
class GyroParams:
    """The ``imu.*`` parameters (see ``GYRO_SPECS`` for units and meanings)."""

    mode: str = 'off'
    scale: float = 1.0
    bias: float = 0.0
    time_offset: float = 0.0
    timeout: float = 0.2
    max_gap: float = 0.08
    max_wait: float = 0.05
    saturation: float = 35.0
    spike: float = 0.5
    arw: float = 2e-3
    bias_sigma: float = 1e-3
    q_bias: float = 1e-8
    q_gain: float = 0.03
    gain_sigma: float = 0.05
    r_floor: float = 0.033
    r_rel: float = 0.42
    huber_k: float = 3.0
    gain_min: float = 0.5
    gain_max: float = 1.5
    fallback_distance: float = 50.0
    standstill: float = 0.02
    yaw_noise_scale: float = 1.0

    def __post_init__(self) -> None:
        if self.mode not in GYRO_MODES:
            raise ValueError(f'imu.mode must be one of {", ".join(GYRO_MODES)}, got {self.mode!r}')

    @classmethod
    def from_values(cls, values: Mapping[str, Any], prefix: str = 'imu.') -> 'GyroParams':
        """Return the parameters of a flat mapping (``imu.mode``, ``imu.scale``, ...), checked."""
        kwargs: dict[str, Any] = {'mode': values.get(prefix + 'mode', 'off')}
        for spec in GYRO_SPECS:
            if prefix + spec.name in values:
                kwargs[_ATTR[spec.name]] = check_value(spec, values[prefix + spec.name], prefix)
        return cls(**kwargs)

    def as_values(self, prefix: str = 'imu.') -> dict[str, Any]:
        """Return the flat ``imu.*`` mapping of these parameters (inverse of from_values)."""
        out: dict[str, Any] = {prefix + 'mode': self.mode}
        for spec in GYRO_SPECS:
            out[prefix + spec.name] = float(getattr(self, _ATTR[spec.name]))
        return out


assert {f.name for f in fields(GyroParams)} == set(_ATTR.values()) | {'mode'}


class GyroStatus(enum.Enum):
    """What happened to a gyro sample (first five), or why an interval has no gyro rate."""

    ACCEPTED = 'accepted'            # kept and usable
    NON_FINITE = 'non_finite'        # NaN or inf: not kept
    SATURATED = 'saturated'          # |rate| >= imu.saturation: kept as a hole
    OLDER = 'older'                  # stamp older than the newest kept: rejected
    CONTRADICTS = 'contradicts'      # interval: covered, but the gyro contradicts the wheels
    CLOCK_RESET = 'clock_reset'      # the gyro clock stepped back (confirmed): history dropped
    DUPLICATE = 'duplicate'          # same stamp as the newest kept: rejected
    COVERED = 'covered'              # interval: the mean rate is known
    NOT_YET = 'not_yet'              # interval end not (yet) bracketed by checked samples
    STALE = 'stale'                  # no usable sample within imu.timeout of the interval end
    GAP = 'gap'                      # a gap longer than imu.max_gap between usable samples
    SATURATED_INSIDE = 'saturated_inside'  # a saturated sample inside the interval
    NO_HISTORY = 'no_history'        # the interval starts before the oldest kept sample
    CLOCK_AHEAD = 'clock_ahead'      # ... by more than max_stamp_step_back: another clock
