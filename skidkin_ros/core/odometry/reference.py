"""The reference input of online calibration: its parameters, its mount and its fault causes.

A second source of motion (lidar odometry, a SLAM, GNSS, visual odometry) publishes stamped
poses of one of the robot's frames (the reference frame, e.g. the lidar) in its own world frame.
Online calibration (:mod:`skidkin_ros.core.online`) compares the wheel odometry with it; this
module holds what the node's parameter schema needs without the calibration code:

* ``ONLINE_SPECS`` and :class:`OnlineParams`: the ``online.*`` parameters (units, ranges);
* :func:`base_pose`: a reference pose of the reference frame, turned into the pose of the base
  frame (``online.mount_*`` is the reference frame's pose on the robot, T_BS):
  T_WB = T_WS T_BS^-1;
* :class:`ReferenceStatus`: what happened to one reference pose, every value a counted cause.

Stamps: ``online.time_offset`` is the reference stamp minus the wheel stamp of the same motion
(> 0: the reference stamps late), so a reference pose stamped t describes wheel time
t - time_offset.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
import enum
import math
from typing import Any, Mapping, Sequence

from skidkin_ros.core.kinematics import residual
from skidkin_ros.core.kinematics.extensions import get_extension
from skidkin_ros.core.kinematics.specs import check_value, INF, ParamSpec
from skidkin_ros.core.timeunits import s_to_ns
from skidkin_ros.errors import ParameterError

__all__ = ['ONLINE_SPECS', 'ONLINE_EXTENSIONS', 'residual_rate_terms', 'rate_extensions',
           'OnlineParams', 'ReferenceStatus', 'base_pose', 'HEADING_MODES']

# Extensions of an augmented model that online calibration learns (with the base model's
# parameters): twist-stage ones that depend on the wheel speeds and the base twist only
# (skidkin_ros.core.online.augmented says why the others are refused), acceleration_slip and the
# residual model (its gains; its coefficients held), which read the base twist's rate.
ONLINE_EXTENSIONS: tuple[str, ...] = ('speed_slip', 'direction_asymmetry', 'lateral_skid',
                                      'icr_offset', 'ratio_yaw_slip', 'acceleration_slip',
                                      'residual_model')
# online.reference_heading: is the reference's heading measured (heading.py)?
HEADING_MODES = ('auto', 'measured', 'unmeasured')
# The residual model's inputs that are rates of the base twist.
RATE_INPUTS = ('dv', 'dw')

ONLINE_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec('time_offset', 's', 0.0, -1.0, 1.0,
              'reference stamp minus the wheel stamp of the same motion (> 0: reference late)'),
    ParamSpec('mount_x', 'm', 0.0, -100.0, 100.0,
              'x of the reference frame (its child_frame_id) in the base frame'),
    ParamSpec('mount_y', 'm', 0.0, -100.0, 100.0,
              'y of the reference frame in the base frame'),
    ParamSpec('mount_yaw', 'rad', 0.0, -math.pi, math.pi,
              'yaw of the reference frame in the base frame'),
    ParamSpec('horizon', 'm', 2.0, 0.0, 100.0,
              "learning segments end after this reference path (the calibrator's h_t)",
              lower_open=True),
    ParamSpec('horizon_rad', 'rad', 1.0, 0.0, 100.0,
              "or after this much turning (the calibrator's h_t_rad)", lower_open=True),
    ParamSpec('memory', 'm', 30.0, 0.0, 1e6,
              'forgetting length: information older than this many metres fades by 1/e',
              lower_open=True),
    ParamSpec('adapt_memory', 'm', 4.0, 0.0, 1e6,
              'forgetting length while adapting to a new ground', lower_open=True),
    ParamSpec('adapt_distance', 'm', 10.0, 0.0, 1e6,
              'travel after a detected change during which adapt_memory applies'),
    ParamSpec('window', '', 16.0, 1.0, 1000.0,
              'learning segments kept per ground and solved again at every new one (older '
              'ones also fade by the memory)'),
    ParamSpec('prior_sigma', '', 0.5, 0.0, 10.0,
              'prior standard deviation of each parameter on a new ground, relative to its '
              'typical magnitude (centred on the old ground: a narrow one pulls the new '
              'ground back toward it)', lower_open=True),
    ParamSpec('min_information', '', 16.0, 0.0, INF,
              'a direction of the parameters is updated only when one segment adds this much '
              'information to it (relative units: 16 = a 25 % standard deviation)',
              lower_open=True),
    ParamSpec('sigma_xy', 'm', 0.02, 0.0, 100.0,
              'standard deviation of a reference position (each pose); used until the '
              "reference's own noise is measured, then bounds it (a quarter to 4x this)",
              lower_open=True),
    ParamSpec('sigma_yaw', 'rad', 0.005, 0.0, 10.0,
              'standard deviation of a reference heading (each pose); the same', lower_open=True),
    ParamSpec('max_rate', 'Hz', 50.0, 0.0, 1e4,
              'reference poses closer than 1/max_rate to the last accepted one are dropped '
              '(counted reference_rate_limited)', lower_open=True),
    ParamSpec('max_gap', 's', 1.0, 0.0, 3600.0,
              'a reference gap longer than this breaks the segment; no reference for this long: '
              'holding', lower_open=True),
    ParamSpec('max_jump', 'm', 0.5, 0.0, 1e6,
              'reference and wheels disagreeing by more than this plus half the wheel travel '
              'between two reference poses: a jump, refused', lower_open=True),
    ParamSpec('max_jump_rad', 'rad', 0.5, 0.0, 100.0,
              'the same for the heading (plus half the wheel rotation)', lower_open=True),
    ParamSpec('stall', 'm', 0.3, 0.0, 1e6,
              'a reference that does not move while the wheels travel this far is stalled',
              lower_open=True),
    ParamSpec('gyro_sigmas', '', 5.0, 0.0, 1e6,
              'with a gyro (imu.mode fuse): a reference whose heading change since the last '
              'pose, or since the segment start, differs from the gyro integrated yaw by more '
              'than this many standard deviations of their noise is refused (counted '
              'reference_gyro) and the segment dropped', lower_open=True),
    ParamSpec('cusum_drift', '', 6.0, 0.0, 1e6,
              'change detection: the CUSUM of segment NEES minus this (3 dof: 3 on average)',
              lower_open=True),
    ParamSpec('cusum_threshold', '', 40.0, 0.0, 1e9,
              'change detection: a CUSUM beyond this is a change of ground', lower_open=True),
    ParamSpec('switch_window', 'm', 0.5, 0.0, 100.0,
              'a known ground is recognised on the last this many metres of reference path',
              lower_open=True),
    ParamSpec('switch_margin', '', 12.0, 0.0, 1e9,
              'another known ground is taken when its NEES on the window is lower by this',
              lower_open=True),
    ParamSpec('max_grounds', '', 4.0, 1.0, 16.0,
              'grounds remembered at once (the least recently used is forgotten)'),
    ParamSpec('delay_tolerance', 's', 0.0, 0.0, 1.0,
              "> 0: the reference's delay is measured online (the offline lag rule); clearly "
              'beyond time_offset by more than this: taken in force (delay_learn) or learning '
              'paused (counted online_reference_delay), and the value to set said; 0 (default): '
              'not checked (0.06 s suggested where time_offset is unknown)'),
    ParamSpec('delay_learn', '', 1.0, 0.0, 1.0,
              '1: a measured delay beyond delay_tolerance becomes the time_offset in force '
              "(learning restarts from the file's parameters with it; at most 3 times, within "
              '-1 to 1 s); 0: learning only pauses'),
)
_ATTR = {spec.name: spec.name for spec in ONLINE_SPECS}


@dataclass(frozen=True)
class OnlineParams:
    """The ``online.*`` parameters (see ``ONLINE_SPECS`` for units and meanings)."""

    enabled: bool = False
    reference_frame_id: str = ''
    reference_child_frame_id: str = ''
    reference_heading: str = 'auto'
    position_only: bool = False
    time_offset: float = 0.0
    mount_x: float = 0.0
    mount_y: float = 0.0
    mount_yaw: float = 0.0
    horizon: float = 2.0
    horizon_rad: float = 1.0
    memory: float = 30.0
    adapt_memory: float = 4.0
    adapt_distance: float = 10.0
    window: float = 16.0
    prior_sigma: float = 0.5
    min_information: float = 16.0
    sigma_xy: float = 0.02
    sigma_yaw: float = 0.005
    max_rate: float = 50.0
    max_gap: float = 1.0
    max_jump: float = 0.5
    max_jump_rad: float = 0.5
    stall: float = 0.3
    gyro_sigmas: float = 5.0
    cusum_drift: float = 6.0
    cusum_threshold: float = 40.0
    switch_window: float = 0.5
    switch_margin: float = 12.0
    max_grounds: float = 4.0
    delay_tolerance: float = 0.0
    delay_learn: float = 1.0

    @classmethod
    def from_values(cls, values: Mapping[str, Any], prefix: str = 'online.') -> 'OnlineParams':
        """Return the parameters of a flat mapping (``online.enabled``, ...), checked."""
        kwargs: dict[str, Any] = {
            'enabled': bool(values.get(prefix + 'enabled', False)),
            'reference_frame_id': str(values.get(prefix + 'reference_frame_id', '')),
            'reference_child_frame_id': str(values.get(prefix + 'reference_child_frame_id',
                                                       '')),
            'reference_heading': str(values.get(prefix + 'reference_heading', 'auto')),
            'position_only': bool(values.get(prefix + 'position_only', False))}
        if kwargs['reference_heading'] not in HEADING_MODES:
            raise ParameterError(f"{prefix}reference_heading: {kwargs['reference_heading']!r} "
                                 f'is not one of {", ".join(HEADING_MODES)} (auto: the '
                                 "pose covariance's yaw variance and the poses decide)")
        for spec in ONLINE_SPECS:
            if prefix + spec.name in values:
                kwargs[_ATTR[spec.name]] = check_value(spec, values[prefix + spec.name], prefix)
        return cls(**kwargs)

    @property
    def time_offset_ns(self) -> int:
        return s_to_ns(self.time_offset)

    def disagrees(self, miss_m: float, travel_m: float, miss_rad: float = 0.0,
                  turn_rad: float = 0.0, slack_m: float = 0.0) -> bool:
        """Return whether the reference misses the wheels beyond any ground (``max_jump``).

        The one rule for a pose (the gates) and a segment (the learner): ``max_jump`` plus half
        the wheels' travel (plus ``slack_m``, e.g. an antenna's lever on a turn), or
        ``max_jump_rad`` plus half their turn.
        """
        return (miss_m > self.max_jump + 0.5 * travel_m + slack_m
                or abs(miss_rad) > self.max_jump_rad + 0.5 * abs(turn_rad))

    def frames_match(self, frame_id: str, child_frame_id: str) -> bool:
        """Return whether a pose's frames are the configured ones (empty: any)."""
        return ((not self.reference_frame_id or frame_id == self.reference_frame_id)
                and (not self.reference_child_frame_id
                     or child_frame_id == self.reference_child_frame_id))


assert ({f.name for f in fields(OnlineParams)}
        == set(_ATTR.values()) | {'enabled', 'reference_frame_id', 'reference_child_frame_id',
                                  'reference_heading', 'position_only'})


class ReferenceStatus(enum.Enum):
    """What happened to one reference pose (the value is the counter's name)."""

    ACCEPTED = 'reference_accepted'          # used: a segment end, a window, or the next start
    NON_FINITE = 'reference_non_finite'      # NaN or inf in the pose: refused
    BAD_STAMP = 'reference_bad_stamp'        # zero or negative stamp: refused
    FUTURE = 'reference_future'              # max_gap (>= 1 s) ahead of the wheels
    OLDER = 'reference_older'                # not after the last accepted stamp: refused
    RATE_LIMITED = 'reference_rate_limited'  # closer than 1/max_rate to the last one: dropped
    FRAME = 'reference_frame'                # frame_id or child_frame_id not the configured one
    GAP = 'reference_gap'                    # longer than max_gap after the last: segment broken
    JUMP = 'reference_jump'                  # disagrees with the wheels by metres: refused
    STALL = 'reference_stall'                # frozen while the wheels travel: refused
    GYRO = 'reference_gyro'                  # its heading change disagrees with the gyro's
    UNCOVERED = 'reference_uncovered'        # no wheel data at its time: not used
    WHEEL_GAP = 'reference_wheel_gap'        # the wheels have a gap since the last one: restart
    NO_HEADING = 'reference_no_heading'      # its heading is not measured: not learned from


def base_pose(x: float, y: float, yaw: float,
              params: OnlineParams) -> tuple[float, float, float]:
    """Return the base frame's pose from the reference frame's (T_WB = T_WS T_BS^-1)."""
    yaw_b = yaw - params.mount_yaw
    c, s = math.cos(yaw_b), math.sin(yaw_b)
    return (x - (c * params.mount_x - s * params.mount_y),
            y - (s * params.mount_x + c * params.mount_y), yaw_b)


def residual_rate_terms(values: Mapping[str, float]) -> list[str]:
    """Return the residual model's non-zero coefficients on a rate term (dv, dw), by name.

    ``values``: the residual model's parameters by name (``vx_dv``, ..., ``level``); a term
    above the model's level counts as zero, as the model has it.
    """
    level = float(values.get('level', 0.0))
    used = []
    for out, _ in residual.OUTPUTS:
        for term, term_level, _, _ in residual.TERMS:
            name = f'{out}_{term}'
            if (residual.TERM_INPUTS[term] in RATE_INPUTS and term_level <= level
                    and float(values.get(name, 0.0)) != 0.0):
                used.append(name)
    return used


def rate_extensions(extensions: Sequence[str], values: Mapping[str, Any]) -> list[str]:
    """Return the extensions whose twist reads the base twist's rate, with these values.

    ``values``: flat parameters (``augmented.<extension>.<name>``); the residual model counts
    only with a rate term in use (:func:`residual_rate_terms`).
    """
    out = []
    for name in extensions:
        if not get_extension(name).uses_rate:
            continue
        if name == 'residual_model':
            prefix = f'augmented.{name}.'
            if not residual_rate_terms({key[len(prefix):]: value for key, value in
                                        values.items() if key.startswith(prefix)}):
                continue
        out.append(name)
    return out
