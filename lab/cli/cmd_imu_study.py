"""``python -m lab.cli imu-study``: off, adapt and fuse on simulated ground changes."""

from __future__ import annotations

import argparse

from lab.studies.imu import CASES, run_study, TABLE_HEADER
from skidkin_ros.cli.common import say

__all__ = ['add_parser']


def run(args: argparse.Namespace) -> int:
    say(f'eps_t m/m / eps_theta deg/m, medians; seeds {args.seeds}, drive length s '
        f'{args.duration}')
    for line in TABLE_HEADER:
        say(line)
    for case in run_study(args.cases, tuple(args.seeds), args.duration):
        for row in case.rows():
            say(row)
    return 0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        'imu-study', help='study: the gyro modes on simulated drives that change ground',
        description="Calibrate full_linear on effect-free simulated drives, then run the node's "
        'odometer in imu modes off, adapt and fuse on test drives that stay on that ground, '
        'that move to a low-friction ground halfway, and that cross a low-friction region '
        'again and again; print median eps_t / eps_theta against the model calibrated on the '
        'new ground, the recovery of the learned gain and the NEES at 2 m (about a minute).')
    parser.add_argument('--cases', nargs='+', choices=CASES, default=list(CASES))
    parser.add_argument('--seeds', nargs='+', type=int, default=[11, 12, 13],
                        help='seeds of the test drives (one drive each)')
    parser.add_argument('--duration', type=float, default=120.0, metavar='S',
                        help='length of each test drive')
    parser.set_defaults(run=run)
