"""``skidkin models``: the model and parameter tables, generated from the parameter specs.

``skidkin models`` prints the five models and their parameters (docs/models.md embeds it);
``skidkin models --node`` prints every parameter the node declares, from the node's schema
(``parameter_schema``), grouped by job (docs/node.md embeds it). ``make docs`` pastes both into
the pages, and a test fails when a page and the specs disagree.
"""

from __future__ import annotations

import argparse
import re

from skidkin_ros.core.kinematics.models import MODELS
from skidkin_ros.core.kinematics.specs import GEOMETRY_SPECS
from skidkin_ros.core.odometry.noise import NOISE_SPECS
from skidkin_ros.core.odometry.schema import parameter_schema, SchemaEntry

__all__ = ['add_parser', 'markdown_tables', 'node_parameter_reference']


def _row(cells) -> str:
    return '| ' + ' | '.join(str(c).replace('|', '\\|') for c in cells) + ' |'


def markdown_tables() -> str:
    """Render the models and every parameter spec as Markdown (docs/models.md embeds this)."""
    lines = ['| model | reference | Jacobian J(k), twist = J [ω_l, ω_r] | parameters |',
             '|---|---|---|---|']
    for model in MODELS.values():
        params = ', '.join(f'`{name}`' for name in model.param_names) or '– (r, b only)'
        lines.append(_row([f'`{model.name}`', model.reference, f'`{model.formula}`', params]))
    lines += ['', '| parameter | unit | default | range | meaning |', '|---|---|---|---|---|']
    for spec in GEOMETRY_SPECS:
        lines.append(_row([f'`{spec.name}`', spec.unit, spec.default_doc, spec.range_text(),
                           spec.description]))
    for model in MODELS.values():
        for spec in model.params:
            lines.append(_row([f'`models.{model.name}.{spec.name}`', spec.unit,
                               spec.default_doc, spec.range_text(), spec.description]))
    for spec in NOISE_SPECS:
        lines.append(_row([f'`models.<model>.noise.{spec.name}`', spec.unit, spec.default_doc,
                           spec.range_text(), spec.description]))
    return '\n'.join(lines)


# The node's parameters by job, in the order the reference lists them: (title, name test).
_GROUPS = (
    ('The file and the robot', lambda n: n in ('schema_version', 'robot', 'expected_robot',
                                               'wheel_radius', 'track_width')),
    ('The model and how samples are read',
     lambda n: n in ('model', 'interval', 'wheel_signal', 'input', 'left_wheel_joints',
                     'right_wheel_joints')),
    ('What is published', lambda n: n in ('odom_frame_id', 'base_frame_id', 'publish_tf',
                                          'pose_covariance_diagonal',
                                          'twist_covariance_diagonal',
                                          'use_parameter_covariance', 'max_rate')),
    ('Limits: what a sample must satisfy', lambda n: '.' not in n),
    ('Model parameters (`<model>`: any of the five; the values per model are in '
     '[models.md](models.md))', lambda n: n.startswith('models.')),
    ('The augmented model (`model: augmented`, written by `skidkin diagnose`)',
     lambda n: n.startswith('augmented.')),
    ('The gyro (`imu.*`, see [gyro.md](gyro.md))', lambda n: n.startswith('imu.')),
    ("A drive controller's odometry as the wheel input (`input: odometry`, see "
     '[field-recordings.md](field-recordings.md))', lambda n: n.startswith('controller.')),
    ('Online calibration against a reference (`online.*`, see '
     '[online-calibration.md](online-calibration.md))', lambda n: n.startswith('online.')),
)


def _default_text(entry: SchemaEntry) -> str:
    if entry.spec is not None and entry.spec.default_doc:
        return entry.spec.default_doc
    if entry.kind == 'bool':
        return 'true' if entry.default else 'false'
    if entry.kind in ('string_array', 'double_array'):
        return '[' + ', '.join(f'{v:g}' if isinstance(v, float) else str(v)
                               for v in entry.default) + ']'
    if entry.kind == 'matrix':
        return 'zeros (not known)'
    if entry.kind == 'double_list':
        return 'empty (none)'
    if entry.kind == 'double':
        return f'{entry.default:g}'
    return f'`{entry.default}`' if entry.default != '' else "''"


def _range_text(entry: SchemaEntry) -> str:
    if entry.choices:
        return ', '.join(f'`{c}`' for c in entry.choices)
    if entry.spec is not None:
        return entry.spec.range_text()
    if entry.kind == 'matrix':
        return 'symmetric, positive semi-definite'
    return '–'


def _collapsed(schema: list[SchemaEntry]) -> list[tuple[str, SchemaEntry]]:
    """Every entry once, the per-model noise and covariance entries as ``models.<model>.*``."""
    seen, rows = set(), []
    for entry in schema:
        parts = entry.name.split('.')
        name = entry.name
        if parts[0] == 'models' and (parts[2] in ('noise', 'parameter_covariance')):
            name = '.'.join(['models', '<model>'] + parts[2:])
        elif parts[0] == 'models':
            name = 'models.<model>.<parameter>'
        if name in seen:
            continue
        seen.add(name)
        rows.append((name, entry))
    return rows


def node_parameter_reference() -> str:
    """Render every parameter the node declares as Markdown tables, one per job."""
    rows = _collapsed(parameter_schema())
    done: set[str] = set()
    lines: list[str] = []
    for title, belongs in _GROUPS:
        picked = [(n, e) for n, e in rows if n not in done and belongs(n)]
        if not picked:
            continue
        lines += [f'### {title}', '', '| parameter | type | unit | default | range | meaning |',
                  '|---|---|---|---|---|---|']
        for name, entry in picked:
            done.add(name)
            if name == 'models.<model>.<parameter>':
                lines.append(_row([f'`{name}`', 'double', 'see models.md', 'see models.md',
                                   'see models.md', "the model's own parameters: the table in "
                                   '[models.md](models.md)']))
                continue
            unit = entry.spec.unit if entry.spec is not None else ''
            meaning = entry.spec.description if entry.spec is not None else entry.description
            if name != entry.name:  # one row for every model: drop the one model's names
                meaning = re.sub(r' \([^)]*\)', ' (in the order of models.md)', meaning, count=1)
            lines.append(_row([f'`{name}`', entry.kind.replace('_', ' '), unit or '–',
                               _default_text(entry), _range_text(entry), meaning]))
        lines.append('')
    missing = [n for n, _ in rows if n not in done]
    if missing:  # a new parameter must join a group, or the reference would hide it
        raise AssertionError(f'parameters in no group of the reference: {missing}')
    return '\n'.join(lines).rstrip()


def run(args: argparse.Namespace) -> int:
    print(node_parameter_reference() if args.node else markdown_tables())
    return 0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        'models', help='print the models and their parameters (Markdown)',
        description='Print the five kinematic models and every parameter spec as Markdown tables.')
    parser.add_argument('--node', action='store_true',
                        help="print the node's parameter reference instead (every parameter it "
                             'declares, by job)')
    parser.set_defaults(run=run)
