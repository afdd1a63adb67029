"""``skidkin models``: the model and parameter tables, generated from the parameter specs."""

from __future__ import annotations

import argparse

from skidkin_ros.core.kinematics.models import MODELS
from skidkin_ros.core.kinematics.specs import GEOMETRY_SPECS
from skidkin_ros.core.odometry.noise import NOISE_SPECS

__all__ = ['add_parser', 'markdown_tables']


def _row(cells) -> str:
    return '| ' + ' | '.join(str(c).replace('|', '\\|') for c in cells) + ' |'


def markdown_tables() -> str:
    """Render the models and every parameter spec as Markdown (the README embeds this)."""
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


def run(args: argparse.Namespace) -> int:
    print(markdown_tables())
    return 0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        'models', help='print the models and their parameters (Markdown)',
        description='Print the five kinematic models and every parameter spec as Markdown tables.')
    parser.set_defaults(run=run)
