"""The ``skidkin`` command: parse, call the core, write outputs, set the exit code.

This is the only module family that prints for users. Each subcommand lives in its own module and
registers itself through ``add_parser(subparsers)``; errors derived from SkidkinError become one
line on stderr and their exit code (2 configuration, 3 data, 4 fit, 5 output).
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Sequence

from skidkin_ros import __version__
from skidkin_ros.cli import commands
from skidkin_ros.core.parallel import one_blas_thread
from skidkin_ros.errors import SkidkinError

__all__ = ['main', 'build_parser', 'run_parser']

# Longest error message printed: a message quoting a user's value must not flood the terminal.
MAX_MESSAGE_CHARS = 2000

EPILOG = """examples:
  skidkin simulate --out train_bag --duration 120 --seed 1
  skidkin calibrate train_bag --eval eval_bag --out params.yaml --report report/
  skidkin calibrate drive.csv --split-by calib_step --wheel-radius 0.1651 --track-width 0.555 \\
      --out husky.yaml
  skidkin evaluate eval_bag --params params.yaml
  skidkin predict drive.csv --params params.yaml --out predictions.csv
  skidkin groundtruth train_bag --out traj.csv --tum traj_tum.txt
  skidkin demo --out demo_out
  ros2 run skidkin_ros odom_node --ros-args --params-file params.yaml
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='skidkin', description='Calibrate and evaluate skid-steer wheel odometry models '
        '(Baril et al. 2020) from rosbag2 or ROS 1 recordings or trajectory tables.',
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--version', action='version', version=f'skidkin_ros {__version__}')
    parser.add_argument('-v', '--verbose', action='store_true', help='debug logging')
    parser.add_argument('-q', '--quiet', action='store_true', help='warnings and errors only')
    subparsers = parser.add_subparsers(dest='command', metavar='COMMAND')
    subparsers.required = True
    for module in commands.ALL:
        module.add_parser(subparsers)
    return parser


def _configure_logging(verbose: bool, quiet: bool) -> None:
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    logging.basicConfig(level=level, format='%(levelname)s: %(message)s', stream=sys.stderr)
    for noisy in ('matplotlib', 'PIL'):
        logging.getLogger(noisy).setLevel(logging.WARNING)


def _capped(text: str) -> str:
    """Return an error message cut to MAX_MESSAGE_CHARS (values echoed in it are the user's)."""
    if len(text) <= MAX_MESSAGE_CHARS:
        return text
    return f'{text[:MAX_MESSAGE_CHARS]}... ({len(text) - MAX_MESSAGE_CHARS} more characters cut)'


def main(argv: Sequence[str] | None = None) -> int:
    return run_parser(build_parser(), argv)


def run_parser(parser: argparse.ArgumentParser, argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` with a parser of subcommands and run the one chosen, as ``skidkin`` does.

    Errors derived from SkidkinError become one line on stderr and their exit code; the lab's
    command (``python -m lab.cli``) runs its studies through here too.
    """
    args = parser.parse_args(argv)
    _configure_logging(args.verbose, args.quiet)
    try:
        with one_blas_thread():
            return int(args.run(args) or 0)
    except SkidkinError as err:
        print(f'{parser.prog} {args.command}: error: {_capped(str(err))}', file=sys.stderr)
        return err.exit_code
    except BrokenPipeError:  # output piped into `head`: not an error
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print(f'{parser.prog} {args.command}: interrupted; no partial output was written',
              file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
