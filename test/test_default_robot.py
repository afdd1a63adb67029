"""The default robot (a Husky A200) has one home: DEFAULT_GEOMETRY in core/kinematics/specs.py."""

import argparse
import ast
import io
from pathlib import Path
import tokenize

from skidkin_ros.cli.common import add_geometry_args, geometry_from_args
from skidkin_ros.core.kinematics.specs import DEFAULT_GEOMETRY, Geometry, GEOMETRY_SPECS
from skidkin_ros.sim.simulate import SimConfig

PACKAGE = Path(__file__).resolve().parents[1] / 'skidkin_ros'
HOME = 'core/kinematics/specs.py'
HUSKY_NUMBERS = (0.1651, 0.555)


def _husky_literals(source):
    """Yield the lines of code (not strings or comments) that write a Husky number."""
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.NUMBER and ast.literal_eval(token.string) in HUSKY_NUMBERS:
            yield token.start[0]


def test_the_husky_numbers_are_written_once_in_the_product():
    found = {}
    for path in sorted(PACKAGE.rglob('*.py')):
        relative = path.relative_to(PACKAGE).as_posix()
        for line in _husky_literals(path.read_text()):
            found.setdefault(relative, []).append(line)
    assert list(found) == [HOME] and len(found[HOME]) == len(HUSKY_NUMBERS)


def test_the_scan_sees_a_literal_and_not_a_string():
    assert list(_husky_literals("g = Geometry(0.1651, 0.555)\nhelp = 'else 0.1651'\n")) == [1, 1]


def test_every_default_geometry_is_the_default_robot():
    assert DEFAULT_GEOMETRY == Geometry(0.1651, 0.555)
    assert {s.name: s.default for s in GEOMETRY_SPECS} == DEFAULT_GEOMETRY.as_dict()
    config = SimConfig()
    assert Geometry(config.wheel_radius, config.track_width) == DEFAULT_GEOMETRY
    parser = argparse.ArgumentParser()
    add_geometry_args(parser)
    assert geometry_from_args(parser.parse_args([])) == DEFAULT_GEOMETRY
    assert '0.1651' in parser.format_help() and '0.555' in parser.format_help()
