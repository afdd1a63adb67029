"""``skidkin evaluate``: score a parameters file's models on recordings (relative errors)."""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

from skidkin_ros.adapters.sources import load_sources
from skidkin_ros.atomic import atomic_write_text
from skidkin_ros.cli.common import (add_source_args, check_report_dir, print_notes, say,
                                    source_options)
from skidkin_ros.cli.tables import error_table, imu_table
from skidkin_ros.core.calibration.evaluation import evaluate_models
from skidkin_ros.core.calibration.gyro_windows import evaluate_gyro_mode
from skidkin_ros.core.calibration.holdout import split_holdout
from skidkin_ros.core.calibration.segments import cut_segments, SegmentOptions
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.gyro_params import GYRO_MODES
from skidkin_ros.errors import DataError, OutputError, ParameterError

__all__ = ['add_parser']


def run(args: argparse.Namespace) -> int:
    check_report_dir(args.report, args.force)
    config = OdometryConfig.from_file(args.params)
    sources = load_sources(args.sources, source_options(args))
    print_notes(sources)
    drives = [d for s in sources for d in s.drives]
    if args.split_by:
        drives = split_holdout(drives, 2, key=args.split_by)[1]
    segments = cut_segments(drives, SegmentOptions(horizon_m=args.h_e,
                                                   interval=config['interval']))
    if len(segments) == 0:
        raise DataError(f'no evaluation segment of {args.h_e:g} m in the given data '
                        f'({segments.counts.as_dict()})')
    models = _models_to_score(args.models, config, args.params)
    values = {m: config.model_values[m] for m in models}
    say(f'{len(segments)} segments of h_e = {args.h_e:g} m; parameters from {args.params} '
        f'(active model {config.model}, interval {config["interval"]})')
    if args.imu_mode is None:
        evaluation = evaluate_models(values, config.geometry, segments)
        table = error_table(evaluation, best=config.model)
    else:
        modes = GYRO_MODES if 'all' in args.imu_mode else tuple(dict.fromkeys(args.imu_mode))
        scores = {f'{m} {mode}': evaluate_gyro_mode(config, drives, segments, m, mode)
                  for m in models for mode in modes}
        evaluation = {name: score.evaluation for name, score in scores.items()}
        table = imu_table(scores, config)
    say(table)
    if args.report is not None:
        try:
            args.report.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise OutputError(f'cannot create report folder {args.report}: {err}') from err
        shim = SimpleNamespace(evaluation=evaluation, eval_segments=segments,
                               options=SimpleNamespace(h_e=args.h_e))
        from skidkin_ros.report.figures import error_distributions  # matplotlib: only here

        error_distributions(shim, args.report / 'errors.png')
        page = (f'# skidkin evaluate\n\nParameters: `{args.params}`; sources: '
                + ', '.join(f'`{s.path}`' for s in sources)
                + f'\n\n```\n{table}\n```\n\n![errors](errors.png)\n')
        atomic_write_text(args.report / 'report.md', page, force=True)
        say(f'report: {args.report / "report.md"}')
    return 0


def _models_to_score(requested: list[str] | None, config: OdometryConfig,
                     path: Path) -> list[str]:
    """Return the models to score: all the file holds, or the requested ones if it holds them.

    A model the file does not hold would be scored with its defaults (the ideal differential
    drive) and look like a calibrated one: it is refused when asked for, and named when left out.
    """
    held = list(config.models_in_file)
    if requested:
        unknown = [m for m in requested if m not in config.model_values]
        if unknown:
            raise ParameterError(f'unknown model(s) {", ".join(unknown)}; known: '
                                 f'{", ".join(config.model_values)}')
        missing = [m for m in requested if m not in held]
        if missing:
            raise ParameterError(
                f'model(s) {", ".join(missing)} not in the file {path} (it holds '
                f'{", ".join(held)}); their fit was invalid or they were not calibrated: '
                'recalibrate, or score one of those')
        return list(dict.fromkeys(requested))
    left_out = [m for m in config.model_values if m not in held]
    if left_out:
        say(f'not in the file (not scored): {", ".join(left_out)}')
    return held


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        'evaluate', help="score a parameters file's models on recordings",
        description='Cut the recordings into h_e segments on the ground-truth path and score '
        'every model of the parameters file with the relative errors eps_t (m/m) and eps_theta '
        '(deg/m) of Baril et al. (2020).')
    parser.add_argument('sources', nargs='+', type=Path, help='bag(s) or trajectory table(s)')
    parser.add_argument('--params', type=Path, required=True, help='parameters file')
    parser.add_argument('--models', nargs='+', help='models to score (default: all)')
    parser.add_argument('--h-e', type=float, default=2.0, metavar='M',
                        help='evaluation horizon')
    parser.add_argument('--split-by', metavar='COLUMN',
                        help='score only the drives with an odd value of COLUMN (the held-out '
                        'half of calibrate --split-by COLUMN)')
    parser.add_argument('--imu-mode', nargs='+', choices=GYRO_MODES + ('all',),
                        help="run the node's odometer in these imu modes (off, adapt, fuse, all) "
                        "with the file's imu.* gyro calibration, the learned gain carried from "
                        "drive to drive as in one node; adds the errors at each drive's end")
    parser.add_argument('--report', type=Path, help='folder for report.md and errors.png')
    parser.add_argument('--force', action='store_true', help='overwrite the report')
    add_source_args(parser)
    parser.set_defaults(run=run)
