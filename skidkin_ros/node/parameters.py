"""The node's ROS parameters: declared from the one schema, with descriptors, checked up front.

Every parameter comes from :func:`skidkin_ros.core.odometry.schema.parameter_schema` (the same
names the calibrator writes). Values given on the command line or in a parameters file are
validated by :meth:`OdometryConfig.from_flat` before anything is declared, so a typo or an
out-of-range value gives one clear message naming the parameter and its range instead of
rclpy's type or range exception. ``--params-file`` files are read first as the offline tools read
them (empty, aliases, too large: refused; a duplicate key: a warning), so both agree.
"""

from __future__ import annotations

import array
import dataclasses
import math
from typing import Any, Sequence

import numpy as np
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from skidkin_ros.core.kinematics.specs import Geometry, GEOMETRY_SPECS
from skidkin_ros.core.odometry.config import (implied_interval, OdometryConfig, parameter_schema,
                                              read_params_document, SchemaEntry)
from skidkin_ros.errors import ConfigError

__all__ = ['READ_ONLY', 'parameter_descriptor', 'declare_schema', 'current_flat', 'plain_value',
           'check_params_files']

# Parameters that cannot change while running (the subscriptions depend on them).
READ_ONLY = ('input',)


def parameter_descriptor(entry: SchemaEntry) -> ParameterDescriptor:
    """Return the ROS parameter descriptor of one schema entry.

    Floating-point parameters use dynamic typing so that ``1`` in a YAML file (an integer to
    rclpy) is accepted and converted; the node validates every value itself through
    :meth:`OdometryConfig.from_flat`. A FloatingPointRange is attached only when both bounds are
    finite (rclpy cannot express an open or infinite range).
    """
    descriptor = ParameterDescriptor(name=entry.name, description=entry.description,
                                     read_only=entry.name in READ_ONLY)
    if entry.kind in ('double', 'double_array', 'matrix', 'double_list'):
        descriptor.dynamic_typing = True
        descriptor.additional_constraints = 'integers are accepted and converted to floats'
    spec = entry.spec
    if (entry.kind == 'double' and spec is not None and math.isfinite(spec.lower)
            and math.isfinite(spec.upper)):
        descriptor.floating_point_range = [
            FloatingPointRange(from_value=float(spec.lower), to_value=float(spec.upper),
                               step=0.0)]
        if spec.lower_open or spec.upper_open:
            descriptor.additional_constraints += f'; allowed range {spec.range_text()}'
    if entry.choices:
        descriptor.additional_constraints = 'one of: ' + ', '.join(entry.choices)
    if entry.kind == 'double_array':
        descriptor.additional_constraints += f'; exactly {entry.length} values > 0'
    if entry.kind == 'double_list':
        descriptor.additional_constraints += '; any number of finite values (empty: none)'
    if entry.kind == 'matrix':
        descriptor.additional_constraints += (f'; exactly {entry.length} values, a symmetric '
                                              'positive semi-definite matrix')
    return descriptor


def plain_value(value: Any) -> Any:
    """Return a parameter value with arrays as lists (rclpy hands out array.array)."""
    if isinstance(value, (array.array, tuple, np.ndarray)):
        return list(value)
    return value


def declare_schema(node: Node) -> dict[str, SchemaEntry]:
    """Check the given values, declare the whole schema and return it by name.

    Geometry is declared first: the models' defaults follow it.
    """
    overrides = _check_overrides(node)
    geometry_names = {spec.name for spec in GEOMETRY_SPECS}
    geometry_entries = {entry.name: entry for entry in parameter_schema()
                        if entry.name in geometry_names}
    for entry in geometry_entries.values():
        _declare(node, entry)
    geometry = Geometry(**{name: float(node.get_parameter(name).value)
                           for name in geometry_entries})
    schema = {entry.name: entry for entry in parameter_schema(geometry)}
    # A calibrated file without an interval keeps its meaning (config.implied_interval).
    schema['interval'] = dataclasses.replace(schema['interval'],
                                             default=implied_interval(overrides))
    for name, entry in schema.items():
        if name not in geometry_entries:
            _declare(node, entry)
    return schema


def current_flat(node: Node, schema: Sequence[str]) -> dict[str, Any]:
    """Return the node's current values of the schema's parameters, {name: plain value}."""
    return {name: plain_value(node.get_parameter(name).value) for name in schema}


def _declare(node: Node, entry: SchemaEntry) -> None:
    try:
        node.declare_parameter(entry.name, entry.default, parameter_descriptor(entry))
    except ParameterException as err:
        raise ConfigError(f'parameter {entry.name!r} was refused by ROS: {err}; '
                          f'{entry.description}') from err


def _check_overrides(node: Node) -> dict[str, Any]:
    """Validate the values given on the command line / in files before declaring them.

    Refuses names the node does not know (typos) and values out of range, naming both; returns
    them (provenance included).
    """
    builtin = set(node._parameters)  # declared by rclpy itself (use_sim_time, ...)
    overrides = {name: plain_value(param.value)
                 for name, param in node._parameter_overrides.items()
                 if name not in builtin}
    OdometryConfig.from_flat(overrides)
    return overrides


def check_params_files(argv: Sequence[str], warnings: list[str] | None = None) -> list[str]:
    """Return one problem per ``--params-file`` that the offline tools would refuse (N16, N31).

    Each file is read as ``skidkin`` reads it (:func:`read_params_document`): missing,
    unreadable, not a regular file, too large, empty, aliases: a problem. A duplicate key is
    appended to ``warnings`` (the last value wins, in rcl as in the offline tools).
    """
    problems = []
    args = list(argv)
    for i, arg in enumerate(args):
        if arg != '--params-file':
            continue
        if i + 1 >= len(args):
            problems.append('--params-file is given without a path')
            continue
        try:
            _, found = read_params_document(args[i + 1])
        except ConfigError as err:
            problems.append(str(err))
            continue
        if warnings is not None:
            warnings.extend(found)
    return problems
