"""The lab's command, ``python -m lab.cli``: the studies behind docs/results.md.

The studies are research, not product: they run from a clone of the repository (the installed
``skidkin`` lists the product's commands only) and go through the same runner as ``skidkin``
(errors as one line and an exit code, one BLAS thread, logging).
"""

from __future__ import annotations

import argparse
from typing import Sequence

from lab.cli import cmd_effects, cmd_estimate, cmd_imu_study
from skidkin_ros.cli.main import run_parser

__all__ = ['COMMANDS', 'build_parser', 'main']

COMMANDS = [cmd_estimate, cmd_effects, cmd_imu_study]

EPILOG = """examples:
  python -m lab.cli estimate --out estimation_out
  python -m lab.cli effects
  python -m lab.cli imu-study
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='python -m lab.cli', description='The studies behind docs/results.md (simulated '
        'experiments; they print the tables of that page).',
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('-v', '--verbose', action='store_true', help='debug logging')
    parser.add_argument('-q', '--quiet', action='store_true', help='warnings and errors only')
    subparsers = parser.add_subparsers(dest='command', metavar='COMMAND')
    subparsers.required = True
    for module in COMMANDS:
        module.add_parser(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    return run_parser(build_parser(), argv)
