"""``python -m lab.cli effects``: the undeclared-effect study, the table of docs/results.md."""

from __future__ import annotations

import argparse

from lab.studies.effects import CASE_NAMES, run_study, TABLE_HEADER
from skidkin_ros.cli.common import say

__all__ = ['add_parser']

NONE = 'none'


def run(args: argparse.Namespace) -> int:
    for line in TABLE_HEADER:
        say(line)
    for case in run_study(args.effects):
        say(case.row())
    return 0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        'effects', help='study: inject each simulated effect, diagnose blind, print the table',
        description='For effect-free data, for every effect the simulator can inject and for '
        'drives with two effects at once (each at a seeded random strength): simulate two '
        'training and three evaluation drives of an edd_symmetric robot with those effects and '
        'ICP-like ground truth, calibrate edd_symmetric, diagnose without being told the '
        'effects, and print one Markdown row: '
        'what was found and the held-out median errors of the base model, the augmented one '
        'and the true model. The whole study takes a few minutes; rows appear as they finish.')
    parser.add_argument('--effects', nargs='+', choices=CASE_NAMES, default=list(CASE_NAMES),
                        metavar='EFFECT',
                        help=f'the cases to run, in order (default: all; {NONE}: effect-free '
                        'data; A+B: both effects at once). Choices: ' + ', '.join(CASE_NAMES))
    parser.set_defaults(run=run)
