"""The odometry configuration: the node's parameter schema and the ROS 2 parameters file.

One schema (``parameter_schema``) lists every parameter the node declares, with type, default,
description and range. The node declares exactly these; the calibrator writes a parameters file
(``/**: ros__parameters:``) with the same names; ``OdometryConfig.from_flat`` validates either.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import datetime
import logging
import math
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
from skidkin_ros import __version__
from skidkin_ros.atomic import atomic_write_text
from skidkin_ros.core.kinematics.augmented import AUGMENTED_NAME, AugmentedModel
from skidkin_ros.core.kinematics.extensions import EXTENSIONS, ordered
from skidkin_ros.core.kinematics.models import get_model, MODELS
from skidkin_ros.core.kinematics.specs import check_value, Geometry, GEOMETRY_SPECS, ParamSpec
from skidkin_ros.core.odometry.controller import CONTROLLER_SPECS, ControllerGeometry
from skidkin_ros.core.odometry.gyro_params import GYRO_MODES, GYRO_SPECS, GyroParams
from skidkin_ros.core.odometry.integrator import IntegratorLimits
from skidkin_ros.core.odometry.interval import DEFAULT_INTERVAL, INTERVALS, LEGACY_INTERVAL
from skidkin_ros.core.odometry.noise import (FALLBACK_POSE_DIAGONAL, FALLBACK_TWIST_DIAGONAL,
                                             NOISE_SPECS, NoiseModel)
from skidkin_ros.core.odometry.reference import ONLINE_SPECS, OnlineParams
from skidkin_ros.core.odometry.residual_uncertainty import (
    coefficient_count, RESIDUAL_EXTENSION, ResidualUncertainty)
from skidkin_ros.core.odometry.uncertainty import (check_parameter_covariance,
                                                   ParameterUncertainty)
from skidkin_ros.core.odometry.wheels import WHEEL_SIGNALS
from skidkin_ros.errors import brief, ConfigError, ParameterError
import yaml

__all__ = [
    'SCHEMA_VERSION',
    'INPUT_MODES',
    'node_default',
    'SchemaEntry',
    'parameter_schema',
    'OdometryConfig',
    'flatten',
    'nest',
    'parse_extensions',
    'models_given',
    'check_model_given',
    'implied_interval',
    'read_params_file',
    'read_params_document',
    'parse_params_text',
    'write_params_file',
    'params_document',
]

SCHEMA_VERSION = 1
INPUT_MODES = ('joint_state', 'wheel_topics', 'odometry')
DEFAULT_LEFT_JOINTS = ['front_left_wheel_joint', 'rear_left_wheel_joint']
DEFAULT_RIGHT_JOINTS = ['front_right_wheel_joint', 'rear_right_wheel_joint']
# A publish-rate cap below this would silence /odom for minutes (1e-300 Hz: for ever).
MIN_RATE_HZ = 0.1
# A parameters file is a few kB; anything near this is not one (and would be read into memory).
MAX_PARAMS_FILE_BYTES = 8 * 1024 * 1024
FRAME_PARAMETERS = ('odom_frame_id', 'base_frame_id')
# ROS integer parameters are 64-bit; a YAML integer beyond them cannot be a parameter (and
# overflows a float: 10**400).
INT64_MAX = 2 ** 63 - 1
# Largest variance (m^2, rad^2, or per metre, second, radian) a covariance parameter may hold:
# beyond it the propagated covariance overflows and the odometry is never published again
# (set_pose's covariance has the same bound).
VARIANCE_LIMIT = 1e12
# A model parameter whose range is open-ended is still a length or a coefficient of a robot:
# beyond this magnitude its twists overflow the covariance propagation.
MAGNITUDE_LIMIT = 1e9

LOG = logging.getLogger(__name__)


@dataclass(frozen=True)
class SchemaEntry:
    """One node parameter: name, type, default, description and range.

    ``kind`` is one of 'double', 'int', 'bool', 'string', 'string_array', 'double_array';
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


def implied_interval(flat: Mapping[str, Any]) -> str:
    """Return the sample-interval convention parameters mean when they do not name one.

    A parameters file written by ``skidkin calibrate`` (it carries ``provenance.*``) before the
    convention existed was fitted with the zero-order hold from the stamp, and its parameters
    (a time offset above all) are right only under it: such a file keeps meaning
    ``starting`` (:data:`LEGACY_INTERVAL`). Anything else takes the default, ``ending``.
    """
    if 'interval' in flat:
        return flat['interval']
    if any(str(name).startswith('provenance.') for name in flat):
        return LEGACY_INTERVAL
    return DEFAULT_INTERVAL


def parse_extensions(text: str) -> tuple[str, ...]:
    """Return the extension names of a comma-separated list, in application order."""
    names = [part.strip() for part in str(text).replace(';', ',').split(',')]
    return ordered([name for name in names if name])


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
                    'JointState names of the left wheels (speed = mean of their velocities)'),
        SchemaEntry('right_wheel_joints', 'string_array', list(DEFAULT_RIGHT_JOINTS),
                    'JointState names of the right wheels (speed = mean of their velocities)'),
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
        SchemaEntry('online.save_path', 'string', '',
                    '~/save_calibration writes here (empty: skidkin_online_<date>.yaml in the '
                    'working directory); an existing file is never overwritten'),
    ]
    entries += [SchemaEntry(f'online.{spec.name}', 'double', spec.default_for(None),
                            f'{spec.description} [{spec.unit}], range {spec.range_text()}', spec)
                for spec in ONLINE_SPECS]
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


def _number(spec: ParamSpec, value: Any, prefix: str = '') -> float:
    """Return a numeric parameter checked against its spec; the value echoed is kept short."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParameterError(
            f'parameter {prefix + spec.name!r} must be a number in {spec.range_text()} '
            f'{spec.unit}, got {brief(value)} ({type(value).__name__})')
    return check_value(spec, value, prefix=prefix)


def models_given(names: Iterable[str]) -> tuple[str, ...]:
    """Return the models whose parameters ``names`` set (ideal_dd needs none), in order."""
    names = set(names)
    return tuple(m.name for m in MODELS.values()
                 if not m.params or any(f'models.{m.name}.{p.name}' in names for p in m.params))


def check_model_given(model: str, given: Iterable[str], source: str) -> None:
    """Refuse to switch to a model whose parameters ``source`` does not hold.

    Its defaults are the ideal differential drive: run under a calibrated model's name, they
    would look calibrated. An augmented model needs its base model's parameters.
    """
    given = tuple(given)
    wanted = model
    if model == AUGMENTED_NAME:
        return
    if wanted not in given:
        raise ParameterError(
            f'model {wanted!r} is not in {source} (it holds {", ".join(given) or "none"}): its '
            'parameters would be the defaults (an ideal drive), not a calibration; calibrate '
            'it, load a file that holds it, or choose one of those')


def _check_integers(flat: Mapping[str, Any]) -> None:
    """Refuse integers no ROS parameter holds (beyond 64 bits), in values and in lists."""
    for name, value in flat.items():
        items = value if isinstance(value, (list, tuple)) else [value]
        for item in items:
            if (isinstance(item, int) and not isinstance(item, bool)
                    and not -INT64_MAX - 1 <= item <= INT64_MAX):
                raise ParameterError(
                    f'parameter {brief(name)} holds an integer of {len(str(abs(item)))} '
                    'digits, beyond the 64-bit integers a ROS parameter holds (|n| < 9.2e18); '
                    'write the value meant (a number within its range, e.g. 1.0)')


def _check_magnitude(entry: SchemaEntry, value: Any) -> None:
    """Refuse values the odometry cannot propagate without overflowing.

    Covariances beyond VARIANCE_LIMIT, open-ended values beyond MAGNITUDE_LIMIT; checked
    before anything adds or multiplies them (1e308 + 1e308 is inf).
    """
    variance = entry.kind in ('matrix', 'double_array') or '.noise.' in entry.name
    if not variance and (entry.spec is None or entry.kind != 'double'
                         or math.isfinite(entry.spec.lower) and math.isfinite(entry.spec.upper)):
        return
    items = value if isinstance(value, (list, tuple)) else [value]
    numbers = [float(v) for v in items if isinstance(v, (int, float)) and not isinstance(v, bool)]
    largest = max((abs(v) for v in numbers if math.isfinite(v)), default=0.0)
    limit = VARIANCE_LIMIT if variance else MAGNITUDE_LIMIT
    if largest > limit:
        what = 'variance' if variance else 'robot parameter'
        raise ParameterError(
            f'parameter {entry.name!r} holds {largest:g}, beyond {limit:g} (the largest '
            f'{what} the odometry can propagate without overflowing: it would never publish '
            f'again); give values within {limit:g}')


def _check_entry(entry: SchemaEntry, value: Any) -> Any:
    _check_magnitude(entry, value)
    if entry.spec is not None:
        if entry.kind == 'int':
            if isinstance(value, bool) or not isinstance(value, int):
                raise ParameterError(
                    f'parameter {entry.name!r} must be an integer, got {brief(value)}')
            return value
        return _number(entry.spec, value, prefix=entry.name[:-len(entry.spec.name)])
    if entry.kind == 'bool' and not isinstance(value, bool):
        raise ParameterError(f'parameter {entry.name!r} must be true or false, got {brief(value)}')
    if entry.kind == 'int' and (isinstance(value, bool) or not isinstance(value, int)):
        raise ParameterError(f'parameter {entry.name!r} must be an integer, got {brief(value)}')
    if entry.kind == 'string':
        if not isinstance(value, str):
            raise ParameterError(f'parameter {entry.name!r} must be a string, got {brief(value)}')
        if entry.choices and value not in entry.choices:
            raise ParameterError(
                f'parameter {entry.name!r} = {brief(value)} is not one of: '
                f'{", ".join(entry.choices)}')
    if entry.kind == 'string_array':
        if (not isinstance(value, (list, tuple)) or not value
                or not all(isinstance(v, str) and v for v in value)):
            raise ParameterError(
                f'parameter {entry.name!r} must be a non-empty list of joint names, got '
                f'{brief(value)}')
        return list(value)
    if entry.kind == 'matrix':
        size = math.isqrt(entry.length)
        if (not isinstance(value, (list, tuple))
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                           for v in value)):
            raise ParameterError(f'parameter {entry.name!r} must be a list of {entry.length} '
                                 f'numbers, got {brief(value)}')
        return check_parameter_covariance(entry.name, value, size).ravel().tolist()
    if entry.kind == 'double_array':
        if (not isinstance(value, (list, tuple)) or len(value) != entry.length
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                           for v in value)):
            raise ParameterError(
                f'parameter {entry.name!r} must be a list of {entry.length} numbers, '
                f'got {brief(value)}')
        values = [float(v) for v in value]
        if not all(math.isfinite(v) and v > 0.0 for v in values):
            raise ParameterError(
                f'parameter {entry.name!r} must hold {entry.length} finite variances > 0 '
                f'(a zero variance makes a filter trust the value blindly), got {values}')
        return values
    return value


def _check_node_values(values: Mapping[str, Any]) -> None:
    """Cross-checks of the node's own parameters that a range alone cannot express."""
    rate = values['max_rate']
    if 0.0 < rate < MIN_RATE_HZ:
        raise ParameterError(
            f"parameter 'max_rate' = {rate!r} Hz would publish odometry less than once every "
            f'{1.0 / MIN_RATE_HZ:g} s; give 0 (every sample) or at least {MIN_RATE_HZ:g} Hz')
    for name in FRAME_PARAMETERS:
        frame = values[name]
        if not frame or frame != frame.strip() or any(c.isspace() for c in frame):
            raise ParameterError(
                f'parameter {name!r} = {brief(frame)} is not a frame id; expected a non-empty '
                'name without spaces (e.g. "odom", "base_link")')
        if frame.startswith('/'):
            raise ParameterError(
                f'parameter {name!r} = {brief(frame)} starts with "/", which tf2 refuses in '
                f'frame ids; write {frame.lstrip("/")!r}')
    if values['input'] == 'odometry':
        ControllerGeometry.from_values(values)  # raises, naming what is missing
        if values['wheel_signal'] != 'velocity':
            raise ParameterError(
                f"parameter 'wheel_signal' = {values['wheel_signal']!r} does not apply to input "
                "odometry: a controller's twist is a velocity; set wheel_signal velocity")
    if values['odom_frame_id'] == values['base_frame_id']:
        raise ParameterError(
            f'odom_frame_id and base_frame_id are both {values["odom_frame_id"]!r}; the odometry '
            'is the pose of one frame in another: give two different frames')


@dataclass(frozen=True)
class OdometryConfig:
    """Validated node configuration (everything the node needs, nothing ROS-specific)."""

    model: str
    geometry: Geometry
    model_values: Mapping[str, Mapping[str, float]]
    noise: Mapping[str, NoiseModel | None]
    values: Mapping[str, Any] = field(repr=False, default_factory=dict)
    augmented_base: str = 'ideal_dd'
    augmented_extensions: tuple[str, ...] = ()
    augmented_values: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    # Models whose parameters the source gave (ideal_dd needs none): the others hold defaults.
    models_in_file: tuple[str, ...] = ()

    def __getitem__(self, name: str) -> Any:
        return self.values[name]

    def bound_model(self, name: str | None = None):
        """Return the model to run (an augmented model is a stateful twist source)."""
        name = name or self.model
        if name == AUGMENTED_NAME:
            structure = AugmentedModel(self.augmented_base, self.augmented_extensions)
            base = get_model(self.augmented_base).bind(
                self.model_values[self.augmented_base], self.geometry)
            return structure.bind(base, {ext: self.augmented_values[ext]
                                         for ext in self.augmented_extensions})
        return get_model(name).bind(self.model_values[name], self.geometry)

    @property
    def limits(self) -> IntegratorLimits:
        """Return the integrator's plausibility limits: max_dt, wheel speed and acceleration."""
        return IntegratorLimits(
            max_dt_s=self.values['max_dt'], max_wheel_speed_rad_s=self.values['max_wheel_speed'],
            max_wheel_acceleration_rad_s2=self.values['max_wheel_acceleration'])

    @property
    def active_parameter_uncertainty(self) -> ParameterUncertainty | None:
        """Return the parameter covariance to propagate (None: off, unknown or not possible).

        Off when ``use_parameter_covariance`` is false, when the file holds none (all zeros, or
        a file written before it existed), and for an augmented model (its extensions change the
        twist's dependence on the base parameters).
        """
        if not self.values.get('use_parameter_covariance', True):
            return None
        if self.model == AUGMENTED_NAME:
            return self._residual_uncertainty()
        if self.noise.get(self.model) is None:
            return None
        model = get_model(self.model)
        if not model.params:
            return None
        flat = self.values.get(f'models.{model.name}.parameter_covariance')
        if flat is None:
            return None
        size = len(model.params)
        return ParameterUncertainty.of_model(
            model, model.vector(self.model_values[model.name], self.geometry), self.geometry,
            np.asarray(flat, dtype=float).reshape(size, size))

    def _residual_uncertainty(self) -> ResidualUncertainty | None:
        """Return the residual model's coefficient uncertainty (augmented models only)."""
        if RESIDUAL_EXTENSION not in self.augmented_extensions:
            return None
        if self.noise.get(self.augmented_base) is None:
            return None
        flat = self.values.get(f'augmented.{RESIDUAL_EXTENSION}.covariance')
        if flat is None:
            return None
        size = coefficient_count()
        ext = EXTENSIONS[RESIDUAL_EXTENSION]
        values = ext.vector(self.augmented_values[RESIDUAL_EXTENSION])
        return ResidualUncertainty.of(values, np.asarray(flat, dtype=float).reshape(size, size))

    @property
    def online(self) -> OnlineParams:
        """Return the online calibration parameters (online.*; disabled unless set)."""
        return OnlineParams.from_values(self.values)

    @property
    def imu(self) -> GyroParams:
        """Return the gyro parameters (imu.*; mode off unless set)."""
        return GyroParams.from_values(self.values)

    @property
    def active_noise(self) -> NoiseModel | None:
        """Return the noise model in force (an augmented model uses its base model's)."""
        if self.model == AUGMENTED_NAME:
            return self.noise.get(self.augmented_base)
        return self.noise.get(self.model)

    @classmethod
    def from_file(cls, path: str | Path, model: str | None = None,
                  overrides: Mapping[str, Any] | None = None) -> 'OdometryConfig':
        """Read and validate a ROS 2 parameters file; ``model`` replaces the file's model.

        ``overrides``: parameters set on top of the file's (as the node's command line does).
        """
        flat = read_params_file(path)
        if model is not None:
            flat['model'] = model
        flat.update(overrides or {})
        return cls.from_flat(flat)

    @classmethod
    def from_flat(cls, flat: Mapping[str, Any]) -> 'OdometryConfig':
        """Validate a flat {dotted name: value} mapping (node parameters or a loaded file).

        Missing names take the schema default; an unknown name is an error.
        """
        _check_integers(flat)
        geometry_values = {}
        for spec in GEOMETRY_SPECS:
            geometry_values[spec.name] = _number(spec, flat.get(
                spec.name, spec.default_for(None)))
        geometry = Geometry(**geometry_values)
        schema = {entry.name: entry for entry in parameter_schema(geometry)}
        unknown = sorted(set(flat) - set(schema) - {'use_sim_time'}
                         - {n for n in flat if n.startswith(('provenance.', 'qos_overrides.'))})
        if unknown:
            raise ParameterError(f'unknown parameter(s) {brief(unknown, 400)}; see docs/node.md '
                                 'for the parameters the node accepts')
        values = {}
        defaults = {'interval': implied_interval(flat)}
        for name, entry in schema.items():
            values[name] = _check_entry(entry, flat.get(name, defaults.get(name, entry.default)))
        _check_node_values(values)
        if values['schema_version'] != SCHEMA_VERSION:
            raise ConfigError(
                f'parameters file schema_version is {values["schema_version"]}, this version of '
                f'skidkin_ros reads {SCHEMA_VERSION}; recalibrate with this version')
        if values['expected_robot'] and values['robot'] != values['expected_robot']:
            raise ConfigError(
                f'parameters are for robot {values["robot"]!r} but expected_robot is '
                f'{values["expected_robot"]!r}; load the file calibrated for this robot')
        model_values = {}
        noise = {}
        for model in MODELS.values():
            prefix = f'models.{model.name}.'
            raw = {spec.name: values[prefix + spec.name] for spec in model.params}
            model.vector(raw, geometry)  # cross-parameter constraints (e.g. y_l > y_r)
            model_values[model.name] = raw
            if values[prefix + 'noise.calibrated']:
                noise[model.name] = NoiseModel.from_mapping(
                    {spec.name: values[prefix + 'noise.' + spec.name] for spec in NOISE_SPECS},
                    prefix + 'noise.')
            else:
                noise[model.name] = None
        extensions = parse_extensions(values['augmented.extensions'])
        augmented_values = {
            ext.name: {spec.name: values[f'augmented.{ext.name}.{spec.name}']
                       for spec in ext.params}
            for ext in EXTENSIONS.values()}
        for ext in EXTENSIONS.values():
            ext.vector(augmented_values[ext.name])
        if values['model'] != AUGMENTED_NAME:
            get_model(values['model'])
        _check_online(values)
        given = models_given(flat)
        return cls(values['model'], geometry, model_values, noise, values,
                   values['augmented.base'], extensions, augmented_values, given)


def _check_online(values: Mapping[str, Any]) -> None:
    """Refuse online calibration where it cannot run (a clear message instead of a surprise)."""
    if not values['online.enabled']:
        return
    model = values['model']
    if model == AUGMENTED_NAME:
        raise ConfigError('online.enabled: an augmented model cannot be learned online yet; run '
                          'its base model (model: ' + values['augmented.base'] + ') or turn '
                          'online.enabled off')
    if not get_model(model).params:
        raise ConfigError(f'online.enabled: model {model} has no parameter to learn; choose a '
                          'calibrated model (e.g. edd_asymmetric, full_linear)')
    if values['imu.mode'] == 'adapt':
        raise ConfigError('online.enabled with imu.mode adapt: both would learn the yaw rate; '
                          'use imu.mode fuse or off with online calibration')


def flatten(tree: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """Turn nested YAML into ROS parameter names: {'a': {'b': 1}} -> {'a.b': 1}."""
    flat = {}
    for key, value in tree.items():
        name = f'{prefix}{key}'
        if isinstance(value, Mapping):
            flat.update(flatten(value, name + '.'))
        else:
            flat[name] = value
    return flat


def nest(flat: Mapping[str, Any]) -> dict[str, Any]:
    """Inverse of :func:`flatten`."""
    tree: dict[str, Any] = {}
    for name, value in flat.items():
        node = tree
        *parents, leaf = name.split('.')
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return tree


class _ParamsLoader(yaml.SafeLoader):
    """PyYAML's safe loader, made to read a parameters file as ROS does.

    Aliases (``*name``) and merge keys (``<<``) are refused before anything is expanded: ROS's
    parser refuses them too, and a few hundred bytes of nested aliases expand to gigabytes (an
    "alias bomb"). A key given twice in one mapping is noted in ``duplicates`` (the last value
    wins, in ROS as here).
    """

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self.duplicates: list[str] = []

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None, None, f'the alias *{event.anchor} is not allowed in a parameters file (ROS '
                'refuses aliases too); write the value out', event.start_mark)
        return super().compose_node(parent, index)

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        seen: set[str] = set()
        for key_node, _ in node.value:
            if key_node.tag == 'tag:yaml.org,2002:merge':
                raise yaml.constructor.ConstructorError(
                    None, None, 'merge keys (<<) are not allowed in a parameters file (ROS does '
                    'not expand them); write the values out', key_node.start_mark)
            if isinstance(key_node, yaml.ScalarNode):
                if key_node.value in seen:
                    self.duplicates.append(f'key {brief(key_node.value)} is given twice (line '
                                           f'{key_node.start_mark.line + 1}); the last value wins')
                seen.add(key_node.value)
        return super().construct_mapping(node, deep=deep)


def parse_params_text(text: str, source: str | Path) -> tuple[Mapping[str, Any], list[str]]:
    """Parse the text of a parameters file; return (document, warnings) or raise ConfigError.

    Refused, as the node refuses them: an empty document or one that is not a mapping, aliases
    and merge keys. A duplicate key is a warning (the last value wins, in the node too).
    """
    loader = _ParamsLoader(text)
    try:
        document = loader.get_single_data()
    except yaml.YAMLError as err:
        raise ConfigError(f'parameters file {source} is not valid YAML: '
                          f'{" ".join(str(err).split())}') from err
    except RecursionError as err:
        raise ConfigError(f'parameters file {source} nests too deeply to be a parameters '
                          'file') from err
    finally:
        loader.dispose()
    if not isinstance(document, Mapping) or not document:
        raise ConfigError(f'parameters file {source} is empty or not a mapping; expected '
                          '"/**: ros__parameters: ..."')
    return document, [f'parameters file {source}: {text}' for text in loader.duplicates]


def read_params_document(path: str | Path) -> tuple[Mapping[str, Any], list[str]]:
    """Read and parse a parameters file (see :func:`parse_params_text`); refuse what is not one.

    The path must be a regular file (not a folder, a device like /dev/zero or a pipe) of at
    most ``MAX_PARAMS_FILE_BYTES``, in UTF-8.
    """
    source = Path(path)
    if not source.exists():
        raise ConfigError(f'parameters file {source} does not exist')
    if source.is_dir():
        raise ConfigError(f'parameters file {source} is a directory, expected a YAML file')
    if not source.is_file():
        raise ConfigError(f'parameters file {source} is not a regular file (a device or a pipe?); '
                          'expected a YAML file')
    try:
        with source.open('rb') as stream:
            data = stream.read(MAX_PARAMS_FILE_BYTES + 1)
        if len(data) > MAX_PARAMS_FILE_BYTES:
            raise ConfigError(f'parameters file {source} is larger than '
                              f'{MAX_PARAMS_FILE_BYTES // (1024 * 1024)} MiB; a parameters file '
                              'is a few kB: is it the right file?')
        text = data.decode('utf-8')
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f'parameters file {source} cannot be read: {err}') from err
    return parse_params_text(text, source)


def read_params_file(path: str | Path) -> dict[str, Any]:
    """Read a ROS 2 parameters file and return the flat parameters of its first node entry.

    Warnings (a duplicate key) are logged.
    """
    source = Path(path)
    document, warnings = read_params_document(source)
    for warning in warnings:
        LOG.warning(warning)
    for node_name, body in document.items():
        if isinstance(body, Mapping) and isinstance(body.get('ros__parameters'), Mapping):
            return flatten(body['ros__parameters'])
        raise ConfigError(f'parameters file {source}: entry {brief(node_name)} has no '
                          '"ros__parameters" mapping')
    raise ConfigError(f'parameters file {source} has no node entry')


def _yaml_float(value: float) -> float:
    return float(value)


def _ros_value(value: Any) -> Any:
    """Make a provenance value a valid ROS parameter: no None, no mixed or nested lists."""
    if value is None:
        return ''
    if isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    if isinstance(value, (list, tuple)):
        items = [_ros_value(v) for v in value]
        kinds = {type(v) for v in items}
        if not items:
            return ''
        if len(kinds) == 1 and kinds <= {bool, int, float, str}:
            return items
        if kinds <= {int, float}:
            return [float(v) for v in items]
        return [str(v) for v in items]
    return str(value)


def params_document(config_values: Mapping[str, Any],
                    provenance: Mapping[str, Any] | None = None) -> str:
    """Render flat parameters as a ROS 2 parameters file (floats always written as floats)."""
    flat = {'schema_version': SCHEMA_VERSION}
    schema = {entry.name: entry for entry in parameter_schema()}
    for name, value in config_values.items():
        entry = schema.get(name)
        if entry is not None and entry.kind == 'double':
            value = _yaml_float(value)
        elif entry is not None and entry.kind in ('double_array', 'matrix'):
            value = [float(v) for v in value]
        flat[name] = value
    prov = dict(provenance or {})
    prov.setdefault('tool', f'skidkin_ros {__version__}')
    prov.setdefault('date', datetime.datetime.now(datetime.timezone.utc).isoformat(
        timespec='seconds'))
    flat.update({f'provenance.{k}': _ros_value(v) for k, v in flatten(prov).items()})
    body = {'/**': {'ros__parameters': nest(flat)}}
    header = ('# skidkin_ros parameters file (ROS 2). Load with:\n'
              '#   ros2 run skidkin_ros odom_node --ros-args --params-file THIS_FILE\n')
    return header + yaml.safe_dump(body, sort_keys=False, default_flow_style=None, width=99)


def write_params_file(path: str | Path, config_values: Mapping[str, Any],
                      provenance: Mapping[str, Any] | None = None,
                      force: bool = False) -> Path:
    """Validate, then write atomically; an existing file needs ``force``."""
    OdometryConfig.from_flat(dict(config_values))
    return atomic_write_text(path, params_document(config_values, provenance), force=force)
