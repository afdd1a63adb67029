"""The odometry configuration: validating parameters against the node's schema.

One schema (``parameter_schema``, in :mod:`skidkin_ros.core.odometry.schema`) lists every
parameter the node declares, with type, default, description and range. The node declares exactly
these; the calibrator writes a parameters file (``/**: ros__parameters:``, read and rendered in
:mod:`skidkin_ros.core.odometry.params_file`) with the same names; ``OdometryConfig.from_flat``
validates either, and ``write_params_file`` validates before writing. The names of the schema and
the parameters file are re-exported here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from skidkin_ros.atomic import atomic_write_text
from skidkin_ros.core.kinematics.augmented import AUGMENTED_NAME, AugmentedModel
from skidkin_ros.core.kinematics.extensions import EXTENSIONS, ordered
from skidkin_ros.core.kinematics.models import get_model, KinematicModel, MODELS
from skidkin_ros.core.kinematics.residual import upgrade_covariance
from skidkin_ros.core.kinematics.specs import check_value, Geometry, GEOMETRY_SPECS, ParamSpec
from skidkin_ros.core.odometry.controller import ControllerGeometry
from skidkin_ros.core.odometry.gyro_params import GyroParams
from skidkin_ros.core.odometry.integrator import IntegratorLimits
from skidkin_ros.core.odometry.interval import DEFAULT_INTERVAL, LEGACY_INTERVAL
from skidkin_ros.core.odometry.model_choice import (  # noqa: F401 (re-exported)
    augmented_given, check_model_given, default_parameters_warning, missing_parameters,
    models_given, models_held, switches_model)
from skidkin_ros.core.odometry.noise import NOISE_SPECS, NoiseModel
# The parameters file and the schema live in their own modules; their names stay importable here.
from skidkin_ros.core.odometry.params_file import (flatten, MAX_PARAMS_FILE_BYTES,  # noqa: F401
                                                   nest, params_document, parse_params_text,
                                                   read_params_document, read_params_file)
from skidkin_ros.core.odometry.reference import (ONLINE_EXTENSIONS, OnlineParams,
                                                 rate_extensions)
from skidkin_ros.core.odometry.residual_uncertainty import (coefficient_count, RESIDUAL_EXTENSION,
                                                            ResidualUncertainty)
from skidkin_ros.core.odometry.saved_grounds import check_list, saved_grounds
from skidkin_ros.core.odometry.schema import (DEFAULT_LEFT_JOINTS,  # noqa: F401
                                              DEFAULT_RIGHT_JOINTS, INPUT_MODES, MIN_RATE_HZ,
                                              node_default, NODE_SPECS, parameter_schema,
                                              SCHEMA_VERSION, SchemaEntry)
from skidkin_ros.core.odometry.uncertainty import (check_parameter_covariance,
                                                   ParameterUncertainty)
from skidkin_ros.errors import brief, ConfigError, ParameterError

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
    'augmented_given',
    'models_held',
    'missing_parameters',
    'default_parameters_warning',
    'check_model_given',
    'switches_model',
    'implied_interval',
    'read_params_file',
    'read_params_document',
    'parse_params_text',
    'write_params_file',
    'params_document',
]

FRAME_PARAMETERS = ('odom_frame_id', 'base_frame_id')
# ROS integer parameters are 64-bit; a YAML integer beyond them cannot be a parameter (and
# overflows a float: 10**400).
INT64_MAX = 2 ** 63 - 1
# Largest variance (m^2, rad^2, or per metre, second, radian) a covariance parameter may hold:
# beyond it the propagated covariance overflows and the odometry is never published again
# (set_pose's covariance has the same bound).
VARIANCE_LIMIT = 1e12
# Smallest non-zero magnitude an entry of a covariance parameter may hold: online calibration
# inverts covariances (a variance of 1e-310 has the information inf: the learner's parameters
# turn NaN); 1e-100 is far below any uncertainty a robot parameter or a sensor has.
VARIANCE_FLOOR = 1e-100
# A model parameter whose range is open-ended is still a length or a coefficient of a robot:
# beyond this magnitude its twists overflow the covariance propagation.
MAGNITUDE_LIMIT = 1e9


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


def _number(spec: ParamSpec, value: Any, prefix: str = '') -> float:
    """Return a numeric parameter checked against its spec; the value echoed is kept short."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParameterError(
            f'parameter {prefix + spec.name!r} must be a number in {spec.range_text()} '
            f'{spec.unit}, got {brief(value)} ({type(value).__name__})')
    return check_value(spec, value, prefix=prefix)


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
    variance = (entry.kind in ('matrix', 'double_array') or '.noise.' in entry.name
                or entry.name == 'online.grounds.covariance')
    open_ended = entry.kind == 'double_list' or (
        entry.spec is not None and entry.kind == 'double'
        and not (math.isfinite(entry.spec.lower) and math.isfinite(entry.spec.upper)))
    if not variance and not open_ended:
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
    tiny = [v for v in numbers if 0.0 < abs(v) < VARIANCE_FLOOR] if variance else []
    if tiny:
        raise ParameterError(
            f'parameter {entry.name!r} holds {tiny[0]:g}, a covariance entry below '
            f'{VARIANCE_FLOOR:g} (its inverse, the information online calibration learns with, '
            f'overflows); write 0 where an entry is meant to be zero, or a value of at least '
            f'{VARIANCE_FLOOR:g}')


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
        if entry.name == f'augmented.{RESIDUAL_EXTENSION}.covariance':
            value = upgrade_covariance(value) or value   # an earlier library's 60 x 60
        return check_parameter_covariance(entry.name, value, size).ravel().tolist()
    if entry.kind == 'double_list':
        return check_list(entry.name, value)
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
    # Whether the source gave augmented.base (augmented_given).
    augmented_in_file: bool = False

    @property
    def held_models(self) -> tuple[str, ...]:
        """Return the models the source gave (:func:`models_held`): the ones it may run."""
        return self.models_in_file + ((AUGMENTED_NAME,) if self.augmented_in_file else ())

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

        Off when ``use_parameter_covariance`` is false and when the file holds none (all zeros, or
        a file written before it existed). An augmented model carries its residual model's
        coefficient covariance only, never the base parameters' (its extensions change the
        twist's dependence on them).
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

    def residual_coefficient_covariance(self) -> np.ndarray | None:
        """Return the residual model's coefficient covariance (square), None without one."""
        if RESIDUAL_EXTENSION not in self.augmented_extensions:
            return None
        flat = self.values.get(f'augmented.{RESIDUAL_EXTENSION}.covariance')
        if flat is None:
            return None
        size = coefficient_count()
        return np.asarray(flat, dtype=float).reshape(size, size)

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
        _check_online(values, geometry)
        given = models_given(flat)
        return cls(values['model'], geometry, model_values, noise, values,
                   values['augmented.base'], extensions, augmented_values, given,
                   augmented_given(flat))


def _check_online(values: Mapping[str, Any], geometry: Geometry) -> None:
    """Refuse online calibration where it cannot run (a clear message instead of a surprise)."""
    if not values['online.enabled']:
        return
    model = values['model']
    if model == AUGMENTED_NAME:
        others = [name for name in parse_extensions(values['augmented.extensions'])
                  if name not in ONLINE_EXTENSIONS]
        if others:
            raise ConfigError(
                f'online.enabled: the extension(s) {others} cannot be learned online (a '
                'learning segment is rolled out from its start: it has no time since the drive '
                'started (terrain_regime) and no state carried in (the lags, time_offset, the '
                "backlash's play per wheel); the "
                'sparse correction has nothing of its own to learn: its terms and coefficients '
                'come from a regression over a whole drive); online calibration learns '
                'augmented models '
                f'built from {list(ONLINE_EXTENSIONS)}: drop the others, run the base model '
                f'(model: {values["augmented.base"]}) or turn online.enabled off')
        rated = rate_extensions(parse_extensions(values['augmented.extensions']), values)
        base = get_model(values['augmented.base'])
        if rated and type(base).rows is KinematicModel.rows:
            raise ConfigError(
                f'online.enabled: {rated} read the rate of the base twist, and the base model '
                f'{base.name} is not linear in the wheel speeds: online calibration takes that '
                "rate from the wheel speeds' rate, exact only for a linear base model; use "
                'edd_symmetric, edd_asymmetric or full_linear as the base, a residual model '
                'without rate terms (level below 3), or turn online.enabled off')
        # every online extension has a fitted parameter: only a bare base can have none
        model = ('' if parse_extensions(values['augmented.extensions'])
                 else values['augmented.base'])
    if model and not get_model(model).params:
        raise ConfigError(f'online.enabled: model {model} has no parameter to learn; choose a '
                          'calibrated model (e.g. edd_asymmetric, full_linear)')
    saved_grounds(values, geometry)   # the remembered grounds fit the model learned
    if values['imu.mode'] == 'adapt':
        raise ConfigError('online.enabled with imu.mode adapt: both would learn the yaw rate; '
                          'use imu.mode fuse or off with online calibration')


def write_params_file(path: str | Path, config_values: Mapping[str, Any],
                      provenance: Mapping[str, Any] | None = None,
                      force: bool = False) -> Path:
    """Validate, then write atomically; an existing file needs ``force``."""
    OdometryConfig.from_flat(dict(config_values))
    return atomic_write_text(path, params_document(config_values, provenance), force=force)
