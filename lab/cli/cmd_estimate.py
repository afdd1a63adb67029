"""``python -m lab.cli estimate``: is the odometry covariance honest, and does a filter gain."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from lab.report.estimation import write_estimation_figures
from lab.studies.estimation import run_estimation_study, StudyOptions
from skidkin_ros.cli.common import check_report_dir, say
from skidkin_ros.core.odometry.interval import INTERVALS

__all__ = ['add_parser']


def run(args: argparse.Namespace) -> int:
    check_report_dir(args.out, args.force, '--out')
    options = StudyOptions.quick() if args.quick else StudyOptions()
    options = replace(options, wheel_stamp_shift_samples=args.stamp_shift, interval=args.interval,
                      parameter_covariance=not args.no_parameter_covariance,
                      noise_time=not args.no_time_noise,
                      truth_noise_m=args.truth_noise[0], truth_noise_rad=args.truth_noise[1])
    study = run_estimation_study(seed=args.seed, options=options)
    figures = write_estimation_figures(args.out, study)
    figure_lines = [f'figure {name}: {path}' for name, path in figures.items()]
    for line in study.summary_lines() + figure_lines:
        say(line)
    return 0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        'estimate',
        help='consistency study: odometry NEES and a reference EKF on simulated drives',
        description='Calibrate on a simulated drive, then on held-out drives measure the '
        'normalised estimation error squared (NEES) of the odometry alone over independent 2 m '
        'windows, and run the reference EKF (skidkin prediction step + 1 Hz noisy position '
        'fixes): its error against odometry alone and its NEES, against the chi2 95 % band.')
    parser.add_argument('--out', type=Path, default=Path('estimation_out'),
                        help='folder for the figures')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--quick', action='store_true', help='smaller study (about 40 s)')
    parser.add_argument('--force', action='store_true', help='overwrite the figures')
    parser.add_argument('--no-parameter-covariance', action='store_true',
                        help="leave the calibration's own uncertainty out of the covariance")
    parser.add_argument('--no-time-noise', action='store_true',
                        help='calibrate the noise without its part per second of motion (the '
                        'model before it existed: per metre, per radian and constant)')
    parser.add_argument('--stamp-shift', type=float, default=0.0, metavar='SAMPLES',
                        help='move every simulated wheel stamp by this many sample periods '
                        '(-0.5 with --interval starting: what midpoint does, no half-sample lag)')
    parser.add_argument('--interval', choices=INTERVALS, default='midpoint',
                        help='sample-interval convention of the calibration and the odometry '
                        "(default midpoint: exact for the simulator's speeds, which are the "
                        "wheels' at each stamp)")
    parser.add_argument('--truth-noise', type=float, nargs=2, default=(0.0, 0.0),
                        metavar=('M', 'RAD'),
                        help='white noise on the calibration ground truth (ICP-like, e.g. '
                        '0.01 0.0035); the test drives are scored against the exact truth')
    parser.set_defaults(run=run)
