"""The ROS 2 parameters file: reading it as ROS does, and rendering one with its provenance.

``flatten``/``nest`` map nested YAML to ROS parameter names and back; the YAML loader refuses
aliases and merge keys (an alias bomb) and notes duplicate keys; ``read_params_file`` returns the
flat parameters of a file's first node entry; ``params_document`` renders flat parameters (floats
written as floats, provenance made valid ROS parameters). Validating before writing is
:func:`skidkin_ros.core.odometry.config.write_params_file`'s job.
"""

from __future__ import annotations

import datetime
import logging
import math
from pathlib import Path
from typing import Any, Mapping

from skidkin_ros import __version__
from skidkin_ros.core.odometry.saved_grounds import GROUND_NAMES
from skidkin_ros.core.odometry.schema import parameter_schema, SCHEMA_VERSION
from skidkin_ros.errors import brief, ConfigError
import yaml

__all__ = [
    'MAX_PARAMS_FILE_BYTES',
    'flatten',
    'nest',
    'parse_params_text',
    'read_params_document',
    'read_params_file',
    'params_document',
]

# A parameters file is a few kB; anything near this is not one (and would be read into memory).
MAX_PARAMS_FILE_BYTES = 8 * 1024 * 1024

LOG = logging.getLogger(__name__)


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
        elif entry is not None and entry.kind in ('double_array', 'matrix', 'double_list'):
            value = [float(v) for v in value or ()]
        if name in GROUND_NAMES and not value:
            continue   # no remembered ground (and rcl reads an empty list as not set)
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
