"""The node's parameter schema: every parameter it declares, with type, default, range and text.

``parameter_schema`` lists them (geometry first: model defaults depend on it); ``NODE_SPECS`` holds
the node's own numeric parameters and ``node_default`` their defaults. Validation against the
schema is :mod:`skidkin_ros.core.odometry.config`'s job.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from skidkin_ros.core.kinematics.augmented import AUGMENTED_NAME
from skidkin_ros.core.kinematics.extensions import EXTENSIONS
from skidkin_ros.core.kinematics.models import MODELS
from skidkin_ros.core.kinematics.specs import Geometry, GEOMETRY_SPECS, ParamSpec
from skidkin_ros.core.odometry.controller import CONTROLLER_SPECS
from skidkin_ros.core.odometry.gyro_params import GYRO_MODES, GYRO_SPECS
from skidkin_ros.core.odometry.interval import DEFAULT_INTERVAL, INTERVALS
from skidkin_ros.core.odometry.noise import (FALLBACK_POSE_DIAGONAL, FALLBACK_TWIST_DIAGONAL,
                                             NOISE_SPECS)
from skidkin_ros.core.odometry.reference import HEADING_MODES, ONLINE_SPECS
from skidkin_ros.core.odometry.residual_uncertainty import coefficient_count, RESIDUAL_EXTENSION
from skidkin_ros.core.odometry.saved_grounds import ground_entries
from skidkin_ros.core.odometry.wheels import WHEEL_SIGNALS

__all__ = [
    'SCHEMA_VERSION',
    'INPUT_MODES',
    'DEFAULT_LEFT_JOINTS',
    'DEFAULT_RIGHT_JOINTS',
    'MIN_RATE_HZ',
    'NODE_SPECS',
    'node_default',
    'SchemaEntry',
    'parameter_schema',
]

SCHEMA_VERSION = 1
INPUT_MODES = ('joint_state', 'wheel_topics', 'odometry')
DEFAULT_LEFT_JOINTS = ['front_left_wheel_joint', 'rear_left_wheel_joint']
DEFAULT_RIGHT_JOINTS = ['front_right_wheel_joint', 'rear_right_wheel_joint']
# A publish-rate cap below this would silence /odom for minutes (1e-300 Hz: for ever).
MIN_RATE_HZ = 0.1


@dataclass(frozen=True)
class SchemaEntry:
    """One node parameter: name, type, default, description and range.

    ``kind`` is one of 'double', 'int', 'bool', 'string', 'string_array', 'double_array',
    'matrix' or 'double_list' (finite numbers, any length; empty: none);
    ``spec`` gives numeric ranges, ``choices`` the allowed strings.
    """

    name: str
    kind: str
    default: Any
    description: str
    spec: ParamSpec | None = None
    choices: tuple[str, ...] = ()
    length: int = 0


def _spec(name: str, unit: str, default: float, lower: float, upper: float, text: str,
          lower_open: bool = False) -> ParamSpec:
    return ParamSpec(name, unit, default, lower, upper, text, lower_open=lower_open)


NODE_SPECS: tuple[ParamSpec, ...] = (
    _spec('max_dt', 's', 0.5, 0.0, 3600.0,
          'longest step integrated; a longer gap is not integrated across', lower_open=True),
    _spec('max_wheel_speed', 'rad/s', 100.0, 0.0, 1e4,
          'wheel speeds beyond this magnitude are rejected as implausible', lower_open=True),
    _spec('input_timeout', 's', 0.5, 0.0, 3600.0,
          'no accepted sample for this long: input reported stale', lower_open=True),
    _spec('pair_tolerance', 's', 0.05, 0.0, 10.0,
          'wheel_topics input: left and right samples are paired within this time',
          lower_open=True),
    _spec('future_tolerance', 's', 0.5, 0.0, 3600.0,
          'stamps further than this ahead of the node clock are rejected', lower_open=True),
    _spec('max_rate', 'Hz', 0.0, 0.0, 1e5,
          f'cap on the odometry publish rate (0: every sample; else at least {MIN_RATE_HZ:g} Hz)'),
    _spec('max_stamp_step_back', 's', 3.0, 0.0, 3600.0,
          'input stamps this far behind the last accepted one (driver restarted, its clock '
          'stepped back) reset the odometry once 3 samples in a row confirm it; a smaller step '
          'back is rejected as older', lower_open=True),
    _spec('max_wheel_acceleration', 'rad/s^2', 500.0, 0.0, 1e6,
          'a wheel speed that changes faster than this from the last accepted sample (measured '
          'over at least 10 ms) is rejected as a glitch', lower_open=True),
)


def node_default(name: str) -> float:
    """Return the default of one of the node's own numeric parameters (e.g. pair_tolerance)."""
    return next(spec.default for spec in NODE_SPECS if spec.name == name)


def _model_entries(geometry: Geometry) -> list[SchemaEntry]:
    entries = []
    for model in MODELS.values():
        for spec in model.params:
            entries.append(SchemaEntry(
                f'models.{model.name}.{spec.name}', 'double', spec.default_for(geometry),
                f'{spec.description} [{spec.unit}], range {spec.range_text()}', spec))
        entries.append(SchemaEntry(
            f'models.{model.name}.noise.calibrated', 'bool', False,
            'true when the noise rates below come from a calibration'))
        for spec in NOISE_SPECS:
            entries.append(SchemaEntry(
                f'models.{model.name}.noise.{spec.name}', 'double', spec.default_for(geometry),
                f'{spec.description} [{spec.unit}], range {spec.range_text()}', spec))
        size = len(model.params)
        if size:
            entries.append(SchemaEntry(
                f'models.{model.name}.parameter_covariance', 'matrix', [0.0] * (size * size),
                'covariance of the calibrated parameters (' + ', '.join(model.param_names)
                + '), row-major; all zeros: not known. Propagated into the pose covariance '
                'when use_parameter_covariance is true', length=size * size))
    return entries


def _augmented_entries() -> list[SchemaEntry]:
    entries = [
        SchemaEntry('augmented.base', 'string', 'ideal_dd',
                    'base model of the augmented model (model: augmented)',
                    choices=tuple(MODELS)),
        SchemaEntry('augmented.extensions', 'string', '',
                    'extensions of the augmented model, comma-separated (e.g. '
                    '"time_offset, lateral_skid"); known: ' + ', '.join(EXTENSIONS)),
    ]
    for ext in EXTENSIONS.values():
        for spec in ext.params:
            entries.append(SchemaEntry(
                f'augmented.{ext.name}.{spec.name}', 'double', spec.default_for(None),
                f'{spec.description} [{spec.unit}], range {spec.range_text()}', spec))
    size = coefficient_count()
    entries.append(SchemaEntry(
        f'augmented.{RESIDUAL_EXTENSION}.covariance', 'matrix', [0.0] * (size * size),
        'posterior covariance of the residual model coefficients (vx_*, vy_*, wz_*), row-major; '
        'all zeros: not known. Propagated into the pose covariance when '
        'use_parameter_covariance is true', length=size * size))
    return entries


def parameter_schema(geometry: Geometry | None = None) -> list[SchemaEntry]:
    """Every parameter the node declares, geometry first (model defaults depend on it)."""
    geometry = geometry or Geometry(GEOMETRY_SPECS[0].default_for(None),
                                    GEOMETRY_SPECS[1].default_for(None))
    entries = [
        SchemaEntry('schema_version', 'int', SCHEMA_VERSION,
                    f'parameters file schema; this node reads version {SCHEMA_VERSION}'),
        SchemaEntry('robot', 'string', '', 'robot the parameters were calibrated for'),
        SchemaEntry('expected_robot', 'string', '',
                    'if set, refuse a parameters file whose robot differs'),
    ]
    entries += [SchemaEntry(spec.name, 'double', geometry.as_dict()[spec.name],
                            f'{spec.description} [{spec.unit}], range {spec.range_text()}', spec)
                for spec in GEOMETRY_SPECS]
    entries += [
        SchemaEntry('model', 'string', 'ideal_dd',
                    'kinematic model to run (augmented: a base model plus extensions, see '
                    'augmented.*)', choices=tuple(MODELS) + (AUGMENTED_NAME,)),
        SchemaEntry('interval', 'string', DEFAULT_INTERVAL,
                    'which interval a wheel sample describes: ending (the one up to its stamp, '
                    'as diff_drive_controller), starting (held from its stamp on) or midpoint '
                    '(trapezoid); a calibrated file without it means starting',
                    choices=INTERVALS),
        SchemaEntry('wheel_signal', 'string', 'velocity',
                    'what a JointState wheel reading integrates: velocity, position (the travel '
                    'between two samples, wraps of continuous joints handled) or auto (the '
                    'positions as position does once they change; the velocities where they are '
                    'missing, not finite or frozen)', choices=WHEEL_SIGNALS),
        SchemaEntry('input', 'string', 'joint_state',
                    'joint_state (sensor_msgs/JointState), wheel_topics (two std_msgs/Float64) '
                    "or odometry (a drive controller's nav_msgs/Odometry twist, with its "
                    'geometry in controller.*)', choices=INPUT_MODES),
        SchemaEntry('left_wheel_joints', 'string_array', list(DEFAULT_LEFT_JOINTS),
                    'JointState names of the left wheels (the side speed is their mean, read '
                    'as wheel_signal says)'),
        SchemaEntry('right_wheel_joints', 'string_array', list(DEFAULT_RIGHT_JOINTS),
                    'JointState names of the right wheels (the side speed is their mean, read '
                    'as wheel_signal says)'),
        SchemaEntry('odom_frame_id', 'string', 'odom', 'frame_id of the published odometry'),
        SchemaEntry('base_frame_id', 'string', 'base_link',
                    'child_frame_id of the published odometry'),
        SchemaEntry('publish_tf', 'bool', False,
                    'broadcast odom -> base_link (needs tf2_ros)'),
        SchemaEntry('zero_stamp_uses_receive_time', 'bool', False,
                    'accept JointState with a zero stamp, using the receive time instead'),
        SchemaEntry('pose_covariance_diagonal', 'double_array', list(FALLBACK_POSE_DIAGONAL),
                    'fixed pose covariance published when no calibration is loaded '
                    '(x, y, z, roll, pitch, yaw)', length=6),
        SchemaEntry('twist_covariance_diagonal', 'double_array', list(FALLBACK_TWIST_DIAGONAL),
                    'fallback twist covariance when no calibration is loaded '
                    '(vx, vy, vz, wx, wy, wz)', length=6),
        SchemaEntry('use_parameter_covariance', 'bool', True,
                    "add the calibration's own uncertainty (models.<model>.parameter_covariance, "
                    'when the file has it) to the published pose covariance'),
    ]
    entries += [SchemaEntry(spec.name, 'double', spec.default_for(geometry),
                            f'{spec.description} [{spec.unit}], range {spec.range_text()}', spec)
                for spec in NODE_SPECS]
    entries += [SchemaEntry(f'controller.{spec.name}', 'double', spec.default_for(None),
                            f'{spec.description} [{spec.unit}], range {spec.range_text()}', spec)
                for spec in CONTROLLER_SPECS]
    entries += _model_entries(geometry)
    entries += _augmented_entries()
    entries += _imu_entries()
    entries += _online_entries()
    return entries


def _online_entries() -> list[SchemaEntry]:
    entries = [
        SchemaEntry('online.enabled', 'bool', False,
                    'learn the model parameters online from a reference odometry on '
                    "reference/odom (nav_msgs/Odometry); off: the file's parameters, as always"),
        SchemaEntry('online.reference_frame_id', 'string', '',
                    'refuse reference poses whose header.frame_id differs (empty: any)'),
        SchemaEntry('online.reference_child_frame_id', 'string', '',
                    'refuse reference poses whose child_frame_id differs (empty: any)'),
        SchemaEntry('online.reference_heading', 'string', 'auto',
                    "is the reference's heading measured? auto: not where the pose covariance's "
                    'yaw variance is 1 rad^2 or more (GNSS converters write 999 or 99999) or '
                    'negative, or where it stays constant while the wheels turn 0.3 rad; '
                    'unmeasured '
                    '(GNSS without heading): its heading is never learned from (counted '
                    'reference_no_heading)', choices=HEADING_MODES),
        SchemaEntry('online.position_only', 'bool', False,
                    'where the reference heading is not measured, learn from its positions '
                    'alone (a base model; no change-of-ground detection; see '
                    'online-calibration.md); off: hold the parameters in force'),
        SchemaEntry('online.save_path', 'string', '',
                    '~/save_calibration writes here (empty: skidkin_online_<date>.yaml in the '
                    'working directory); an existing file is never overwritten'),
    ]
    entries += [SchemaEntry(f'online.{spec.name}', 'double', spec.default_for(None),
                            f'{spec.description} [{spec.unit}], range {spec.range_text()}', spec)
                for spec in ONLINE_SPECS]
    entries += [SchemaEntry(name, kind, default, text)
                for name, kind, default, text in ground_entries()]
    return entries


def _imu_entries() -> list[SchemaEntry]:
    entries = [SchemaEntry('imu.mode', 'string', 'off',
                           'gyro use: off (wheels only), adapt (model yaw rate x a gain learned '
                           'from the gyro) or fuse (the gyro yaw rate replaces the model one)',
                           choices=GYRO_MODES)]
    entries += [SchemaEntry(f'imu.{spec.name}', 'double', spec.default_for(None),
                            f'{spec.description} [{spec.unit}], range {spec.range_text()}', spec)
                for spec in GYRO_SPECS]
    return entries
