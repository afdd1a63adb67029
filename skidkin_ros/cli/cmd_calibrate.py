"""``skidkin calibrate``: recordings in, a parameters file the node loads and a report out."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, Sequence

from skidkin_ros.adapters.sources import load_sources, LoadedSource
from skidkin_ros.atomic import check_writable
from skidkin_ros.cli.common import (add_geometry_args, add_source_args, geometry_from_args,
                                    print_notes, say, source_options)
from skidkin_ros.cli.tables import error_table, parameter_lines
from skidkin_ros.core.calibration.pipeline import (calibrate, CalibrationOptions,
                                                   CalibrationResult, horizon_study,
                                                   result_to_parameters)
from skidkin_ros.core.kinematics.models import get_model, MODEL_NAMES
from skidkin_ros.core.odometry.config import write_params_file
from skidkin_ros.errors import FitError, OutputError
from skidkin_ros.report.page import write_report

__all__ = ['add_parser', 'input_parameters', 'provenance', 'check_report_dir']


def check_report_dir(path: Path | None, force: bool) -> None:
    if path is not None and path.exists() and any(path.iterdir()) and not force:
        raise OutputError(f'report folder {path} exists and is not empty; pass --force to '
                          'overwrite its files')


def input_parameters(sources: Sequence[LoadedSource]) -> dict[str, Any]:
    """Node input parameters (input mode, joint names) as used when reading the recordings."""
    for source in sources:
        wheel = source.wheel_input
        if wheel.get('input') == 'joint_state':
            return {'input': 'joint_state', 'left_wheel_joints': wheel['left_wheel_joints'],
                    'right_wheel_joints': wheel['right_wheel_joints']}
        if wheel.get('input') == 'wheel_topics':
            return {'input': 'wheel_topics'}
    return {}


def provenance(result: CalibrationResult, train: Sequence[LoadedSource],
               evaluate: Sequence[LoadedSource], command: str) -> dict[str, Any]:
    errors = {}
    for name, ev in result.evaluation.items():
        errors[name] = {'eps_t_median_m_per_m': ev.stats_t.median,
                        'eps_t_p90_m_per_m': ev.stats_t.p90,
                        'eps_theta_median_deg_per_m': ev.stats_theta.median,
                        'eps_theta_p90_deg_per_m': ev.stats_theta.p90,
                        'valid': bool(result.fits[name].valid)}
    prov = dict(result.provenance)
    prov.update({'command': command, 'train_sources': [str(s.path) for s in train],
                 'evaluate_sources': [str(s.path) for s in evaluate] or result.holdout,
                 'ground_truth': sorted({s.truth_info.get('ground_truth', 'table')
                                         for s in list(train) + list(evaluate)}),
                 'errors': errors})
    return prov


def _options(args: argparse.Namespace) -> CalibrationOptions:
    return CalibrationOptions(
        h_t=args.h_t, h_e=args.h_e, loss=args.loss, f_scale=args.f_scale,
        n_starts=args.starts, seed=args.seed, models=tuple(args.models),
        sigma_diag=tuple(args.sigma), holdout_every=2 if args.split_by else args.holdout_every,
        holdout_key=args.split_by)


def print_result(result: CalibrationResult) -> None:
    say(f'\nsegments: {len(result.train_segments)} training (h_t = {result.options.h_t:g} m), '
        f'{len(result.eval_segments)} evaluation (h_e = {result.options.h_e:g} m, '
        f'{result.holdout})')
    say(error_table(result.evaluation, result.fits, result.noise, result.best))
    say('\nfitted parameters (± standard error):')
    for line in parameter_lines(result.fits):
        say(line)
    sym = result.fits.get('edd_symmetric')
    if sym is not None and sym.values:
        ratio = sym.values['b_hat'] / result.geometry.track_width
        say(f'  edd_symmetric b_hat / track_width = {ratio:.3f}: the '
            'wheel_separation_multiplier of diff_drive_controller that matches this data '
            f'(its alpha = {sym.values["alpha"]:.3f} would be wheel_radius_multiplier)')
    for warning in result.warnings:
        say(f'  warning: {warning}')


def run(args: argparse.Namespace) -> int:
    check_writable(args.out, args.force)
    check_report_dir(args.report, args.force)
    options = _options(args)
    geometry = geometry_from_args(args)
    if args.wheel_radius is None or args.track_width is None:
        say(f'note: using wheel_radius {geometry.wheel_radius:g} m and track_width '
            f'{geometry.track_width:g} m (pass --wheel-radius/--track-width for your robot)')
    src_opts = source_options(args, geometry)
    train = load_sources(args.train, src_opts)
    evaluate = load_sources(args.eval, src_opts) if args.eval else []
    print_notes(train + evaluate)
    result = calibrate([d for s in train for d in s.drives],
                       [d for s in evaluate for d in s.drives] or None, geometry, options)
    print_result(result)
    base = {'robot': args.robot, **input_parameters(train)}
    flat = result_to_parameters(result, base, allow_invalid=False)
    prov = provenance(result, train, evaluate, 'skidkin calibrate')
    written = write_params_file(args.out, flat, prov, force=args.force)
    say(f'\nbest model: {result.best}  (parameters file: {written}; run the node with\n'
        f'  ros2 run skidkin_ros odom_node --ros-args --params-file {written})')
    if args.report is not None:
        study = None
        if args.horizon_study:
            drives_t = [d for s in train for d in s.drives]
            drives_e = [d for s in evaluate for d in s.drives] or drives_t
            study = horizon_study(drives_t, drives_e, geometry, options, (1.0, 2.0, 5.0),
                                  (0.5, 1.0, 2.0, 5.0))
        page = write_report(result, args.report, force=args.force, study=study)
        say(f'report: {page}')
    invalid = [m for m, f in result.fits.items() if not f.valid and get_model(m).params]
    if invalid and not args.accept_invalid:
        raise FitError(f'fit(s) of {", ".join(invalid)} are invalid (not converged, on a bound '
                       'or not observable; see the warnings) and were not written; the other '
                       'models were. Pass --accept-invalid to exit 0 anyway.')
    return 0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        'calibrate', help='fit every model on recordings and write a parameters file',
        description='Fit the five kinematic models on training recordings (rosbag2 with '
        'kiss-icp ground truth, or trajectory tables), score them on evaluation data as Baril '
        'et al. (2020) do (relative errors per metre on h_e segments), calibrate the noise, and '
        'write a ROS 2 parameters file that odom_node loads as is.')
    parser.add_argument('train', nargs='+', type=Path, help='training bag(s) or table(s)')
    parser.add_argument('--eval', nargs='+', type=Path, default=[],
                        help='evaluation bag(s) or table(s) (default: a hold-out of TRAIN)')
    parser.add_argument('--out', type=Path, required=True, help='parameters file to write')
    parser.add_argument('--report', type=Path, help='folder for the Markdown report and figures')
    parser.add_argument('--force', action='store_true', help='overwrite existing outputs')
    parser.add_argument('--models', nargs='+', choices=MODEL_NAMES, default=list(MODEL_NAMES))
    parser.add_argument('--robot', default='', help='robot name recorded in the file')
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
    parser.add_argument('--accept-invalid', action='store_true',
                        help='exit 0 even when a fit is invalid (it is still not written)')
    add_geometry_args(parser)
    add_source_args(parser)
    parser.set_defaults(run=run)
