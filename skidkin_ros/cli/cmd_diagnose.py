"""``skidkin diagnose``: find what the calibrated model lacks, add it, report before and after."""

from __future__ import annotations

import argparse
from pathlib import Path

from skidkin_ros.adapters.sources import load_sources
from skidkin_ros.atomic import check_writable
from skidkin_ros.cli.common import (add_source_args, check_report_dir, check_split_without_eval,
                                    jobs_arg, print_notes, RoundBars, say, source_options)
from skidkin_ros.core.calibration.diagnosis import diagnose, DiagnosisOptions
from skidkin_ros.core.kinematics.extensions import EXTENSIONS
from skidkin_ros.core.odometry.config import OdometryConfig, read_params_file, write_params_file
from skidkin_ros.core.odometry.interval import INTERVALS
from skidkin_ros.core.parallel import usable_cpus

__all__ = ['add_parser']


def run(args: argparse.Namespace) -> int:
    check_writable(args.out, args.force)
    check_report_dir(args.report, args.force)
    check_split_without_eval(args)
    # The file's own parameters are carried into the written file, so read them as given.
    flat = read_params_file(args.params)
    config = OdometryConfig.from_flat(flat)
    base = config.augmented_base if config.model == 'augmented' else config.model
    if args.base:
        base = args.base
    src_opts = source_options(args)
    train = load_sources(args.train, src_opts)
    evaluate = load_sources(args.eval, src_opts) if args.eval else []
    print_notes(train + evaluate)
    options = DiagnosisOptions(
        candidates=tuple(args.candidates) if args.candidates else DiagnosisOptions().candidates,
        holdout_every=2 if args.split_by else 3, holdout_key=args.split_by, trim=args.trim,
        h_t=args.h_t, h_e=args.h_e, interval=args.interval or config['interval'])
    say(f'sample interval: {options.interval}'
        + (' (given)' if args.interval else f' (from {args.params})'))
    bars = None if args.no_progress else RoundBars()
    try:
        result = diagnose([d for s in train for d in s.drives],
                          [d for s in evaluate for d in s.drives] or None, config.geometry,
                          config.model_values, base, options, jobs=args.jobs, progress=bars)
    finally:
        if bars is not None:
            bars.close()
    for line in result.summary_lines():
        say(line)
    written = write_params_file(args.out, result.to_parameters(flat), result.provenance,
                                force=args.force)
    say(f'parameters file: {written} (model {"augmented" if result.extensions else base}); '
        f'run it with: ros2 run skidkin_ros odom_node --ros-args --params-file {written}')
    if args.report is not None:
        from skidkin_ros.report.diagnosis import write_diagnosis_report  # matplotlib

        say(f'report: {write_diagnosis_report(result, args.report, force=args.force)}')
    return 0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        'diagnose', help='find the effect the calibrated model lacks, add it, report the gain',
        description='Compute residuals of the calibrated model against the ground truth, trace '
        'them against every signal in the data (wheel speeds, their sum, difference, ratio and '
        'derivatives, speed, yaw rate, curvature, v*omega, direction, time, position, IMU, '
        'timing), question the base model (asymmetry, ICR, ROC), fit each named extension (and '
        'a data-driven residual model of the wheel-speed state when none explains the rest), '
        'keep those that remove held-out error by cross-validation with a parsimony rule, and '
        'write a complete parameters file with the augmented model.')
    parser.add_argument('train', nargs='+', type=Path, help='training bag(s) or table(s)')
    parser.add_argument('--params', type=Path, required=True,
                        help='calibrated parameters file (from skidkin calibrate)')
    parser.add_argument('--eval', nargs='+', type=Path, default=[],
                        help='evaluation bag(s) or table(s) (default: a hold-out of TRAIN)')
    parser.add_argument('--out', type=Path, required=True, help='parameters file to write')
    parser.add_argument('--report', type=Path, help='folder for diagnosis.md and figures')
    parser.add_argument('--force', action='store_true', help='overwrite existing outputs')
    parser.add_argument('--base', help="base model (default: the file's model)")
    parser.add_argument('--candidates', nargs='+', choices=list(EXTENSIONS),
                        help='extensions to try (default: all but sparse_correction, which the '
                        'residual_model supersedes)')
    parser.add_argument('--split-by', metavar='COLUMN',
                        help='tables without --eval: even values of COLUMN train, odd evaluate')
    parser.add_argument('--trim', action='store_true',
                        help='trim outlier segments before selecting (can hide real effects)')
    parser.add_argument('--jobs', type=jobs_arg, default=usable_cpus(), metavar='N',
                        help='processes fitting the candidates (default: every usable CPU, '
                        '%(default)s here); the result does not depend on it')
    parser.add_argument('--h-t', type=float, default=2.0, metavar='M')
    parser.add_argument('--h-e', type=float, default=2.0, metavar='M')
    parser.add_argument('--interval', choices=INTERVALS,
                        help="which interval a wheel sample describes (default: the file's "
                        'interval; written to the output file)')
    add_source_args(parser)
    parser.set_defaults(run=run)
