"""``skidkin calibrate``: recordings in, a parameters file the node loads and a report out."""

from __future__ import annotations

import argparse
from pathlib import Path
import sys

from skidkin_ros.adapters.sources import load_sources
from skidkin_ros.atomic import check_writable
from skidkin_ros.cli.common import (add_geometry_args, add_source_args, calibration_provenance,
                                    check_report_dir, check_split_without_eval,
                                    geometry_from_args, input_parameters, print_calibration,
                                    print_notes, say, source_options)
from skidkin_ros.core.calibration.pipeline import (calibrate_interval, CalibrationOptions,
                                                   horizon_study, result_to_parameters,
                                                   SELECTIONS, TRAIN_SEGMENTS)
from skidkin_ros.core.calibration.weighting import WEIGHTINGS
from skidkin_ros.core.kinematics.models import get_model, MODEL_NAMES
from skidkin_ros.core.odometry.config import write_params_file
from skidkin_ros.core.odometry.interval import INTERVALS
from skidkin_ros.errors import FitError

__all__ = ['add_parser']


def _deprecations(args: argparse.Namespace) -> None:
    """Say what the deprecated --accept-invalid does now (it still undoes --strict)."""
    if not args.accept_invalid:
        return
    undo = 'it undoes --strict; drop both' if args.strict else 'it does nothing; drop it'
    print(f'note: --accept-invalid is deprecated ({undo}): an invalid fit that was not selected '
          'is a warning by default, and is never written', file=sys.stderr, flush=True)
    args.strict = False


def _options(args: argparse.Namespace) -> CalibrationOptions:
    return CalibrationOptions(
        h_t=args.h_t, h_e=args.h_e, loss=args.loss, f_scale=args.f_scale,
        n_starts=args.starts, seed=args.seed, models=tuple(args.models),
        sigma_diag=tuple(args.sigma), holdout_every=2 if args.split_by else args.holdout_every,
        holdout_key=args.split_by, weighting=args.weighting, selection=args.selection,
        segments=args.segments)


def _print_interval(result) -> None:
    """Say which sample-interval convention was used, and how the others did."""
    chosen = result.options.interval
    if not result.interval_errors:
        say(f'\nsample interval: {chosen} (given)')
        return
    say(f'\nsample interval: {chosen} (chosen on the evaluation segments; {result.best}, '
        'median eps_t [m/m] / eps_theta [deg/m]):')
    for interval, (eps_t, eps_th) in result.interval_errors.items():
        mark = '  <- written' if interval == chosen else ''
        say(f'  {interval:<9} {eps_t:.4f} / {eps_th:.3f}{mark}')


def run(args: argparse.Namespace) -> int:
    _deprecations(args)
    check_writable(args.out, args.force)
    check_report_dir(args.report, args.force)
    check_split_without_eval(args)
    options = _options(args)
    geometry = geometry_from_args(args)
    if args.wheel_radius is None or args.track_width is None:
        say(f'note: using wheel_radius {geometry.wheel_radius:g} m and track_width '
            f'{geometry.track_width:g} m (pass --wheel-radius/--track-width for your robot)')
    src_opts = source_options(args)
    train = load_sources(args.train, src_opts)
    evaluate = load_sources(args.eval, src_opts) if args.eval else []
    print_notes(train + evaluate)
    intervals = INTERVALS if args.interval == 'auto' else (args.interval,)
    result = calibrate_interval([d for s in train for d in s.drives],
                                [d for s in evaluate for d in s.drives] or None, geometry,
                                options, intervals)
    print_calibration(result)
    _print_interval(result)
    base = {'robot': args.robot, **input_parameters(train)}
    flat = result_to_parameters(result, base, allow_invalid=False)
    prov = calibration_provenance(result, train, evaluate, 'skidkin calibrate')
    written = write_params_file(args.out, flat, prov, force=args.force)
    say(f'\nbest model: {result.best}  (parameters file: {written}; run the node with\n'
        f'  ros2 run skidkin_ros odom_node --ros-args --params-file {written})')
    if args.report is not None:
        study = None
        if args.horizon_study:
            drives_t = [d for s in train for d in s.drives]
            drives_e = [d for s in evaluate for d in s.drives] or drives_t
            # result.options: the interval the calibration chose, not the default
            study = horizon_study(drives_t, drives_e, geometry, result.options,
                                  (1.0, 2.0, 5.0), (0.5, 1.0, 2.0, 5.0))
        from skidkin_ros.report.page import write_report  # matplotlib: only for a report

        page = write_report(result, args.report, force=args.force, study=study)
        say(f'report: {page}')
    invalid = [m for m, f in result.fits.items() if not f.valid and get_model(m).params]
    if invalid and args.strict:
        raise FitError(f'fit(s) of {", ".join(invalid)} are invalid (not converged, on a bound '
                       'or not observable; see the warnings) and were not written; the other '
                       'models were. Without --strict this is a warning.')
    if invalid:
        say(f'warning: fit(s) of {", ".join(invalid)} are invalid (not converged, on a bound or '
            f'not observable; see the warnings above) and were not written; the written model '
            f'{result.best} is valid (--strict makes this exit 4)')
    return 0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        'calibrate', help='fit every model on recordings and write a parameters file',
        description='Fit the five kinematic models on training recordings (rosbag2 or ROS 1 '
        'bags with kiss-icp ground truth, or trajectory tables), score them on evaluation data '
        'as Baril et al. (2020) do (relative errors per metre on h_e segments), calibrate the '
        'noise, and write a ROS 2 parameters file that odom_node loads as is.')
    parser.add_argument('train', nargs='+', type=Path, help='training bag(s) or table(s)')
    parser.add_argument('--eval', nargs='+', type=Path, default=[],
                        help='evaluation bag(s) or table(s) (default: a hold-out of TRAIN)')
    parser.add_argument('--out', type=Path, required=True, help='parameters file to write')
    parser.add_argument('--report', type=Path, help='folder for the Markdown report and figures')
    parser.add_argument('--force', action='store_true', help='overwrite existing outputs')
    parser.add_argument('--models', nargs='+', choices=MODEL_NAMES, default=list(MODEL_NAMES))
    parser.add_argument('--robot', default='', help='robot name recorded in the file')
    parser.add_argument('--interval', choices=('auto',) + INTERVALS, default='auto',
                        help='which interval a wheel sample describes: auto (chosen on the '
                        'evaluation data, default), ending, starting or midpoint')
    parser.add_argument('--split-by', metavar='COLUMN',
                        help='tables without --eval: even values of COLUMN train, odd evaluate '
                        '(e.g. calib_step)')
    parser.add_argument('--holdout-every', type=int, default=3,
                        help='without --eval: 1 in N drives (or 60 s blocks) evaluates')
    parser.add_argument('--h-t', type=float, default=2.0, metavar='M', help='training horizon')
    parser.add_argument('--h-e', type=float, default=2.0, metavar='M',
                        help='evaluation horizon')
    parser.add_argument('--sigma', nargs=3, type=float, default=[1.0, 1.0, 1.0],
                        metavar=('X', 'Y', 'YAW'), help='diagonal of the loss covariance')
    parser.add_argument('--loss', choices=('linear', 'soft_l1', 'huber', 'cauchy'),
                        default='linear', help='robust loss of the fit')
    parser.add_argument('--f-scale', type=float, default=1.0, help='robust loss scale')
    parser.add_argument('--starts', type=int, default=8, help='starts for multi-start fits')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--horizon-study', action='store_true',
                        help='add the h_t x h_e study figure to the report')
    parser.add_argument('--strict', action='store_true',
                        help='exit 4 when any fit is invalid, even one that was not selected '
                        '(default: a warning; the written model is always a valid fit)')
    # Deprecated: an invalid fit that was not selected is a warning by default, so
    # the flag only undid --strict. Still taken (scripts keep working), with a note; not in --help.
    parser.add_argument('--accept-invalid', action='store_true', help=argparse.SUPPRESS)
    parser.add_argument('--weighting', choices=WEIGHTINGS, default='iterated',
                        help='loss weights: iterated (each segment by the covariance the noise '
                        'model predicts for it, refitted until the parameters settle) or fixed '
                        '(--sigma for every segment)')
    parser.add_argument('--segments', choices=TRAIN_SEGMENTS, default='rotation',
                        help='training segments: rotation (default: closed after --h-t of path '
                        'or 1 rad of turning, whichever comes first, so spins are fitted too), '
                        'paper (after --h-t of path only, as Baril et al. 2020) or time '
                        '(windows of 2 s)')
    parser.add_argument('--selection', choices=SELECTIONS, default='likelihood',
                        help='best-model rule: held-out likelihood (counts heading) or the '
                        "paper's eps_t + eps_theta")
    add_geometry_args(parser)
    add_source_args(parser)
    parser.set_defaults(run=run)
