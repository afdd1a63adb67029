"""Arguments and output helpers shared by the ``skidkin`` subcommands.

The one home of what more than one command needs: the command modules (``cmd_*``) import from
here, never from each other (``test/test_layering.py``).
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
import sys
from typing import Any, Iterable, Sequence

from skidkin_ros.adapters.cluster import check_cluster_address
from skidkin_ros.adapters.lidar_chunks import ChunkOptions
from skidkin_ros.adapters.lidar_gt import IcpConfig
from skidkin_ros.adapters.sources import extrinsic_from_xyz_rpy, LoadedSource, SourceOptions
from skidkin_ros.atomic import check_writable_dir
from skidkin_ros.cli.progress import Progress
from skidkin_ros.cli.tables import error_table, parameter_lines
from skidkin_ros.core.calibration.results import CalibrationResult
from skidkin_ros.core.kinematics.specs import DEFAULT_GEOMETRY, Geometry
from skidkin_ros.core.odometry.controller import ControllerGeometry
from skidkin_ros.core.odometry.wheels import WHEEL_SIGNALS
from skidkin_ros.core.parallel import usable_cpus
from skidkin_ros.errors import ConfigError, ParameterError

__all__ = ['add_source_args', 'add_geometry_args', 'source_options', 'geometry_from_args',
           'say', 'print_notes', 'default_cache_dir', 'jobs_arg', 'stride_arg', 'RoundBars',
           'check_report_dir', 'check_split_without_eval', 'input_parameters',
           'calibration_provenance', 'print_calibration', 'controller_from_args',
           'plain_reference_lines']


def say(*parts: object) -> None:
    """Print a line for the user (stdout)."""
    print(*parts, flush=True)


def print_notes(sources: Iterable[LoadedSource]) -> None:
    for source in sources:
        for note in source.notes:
            print(f'  note: {note}', file=sys.stderr, flush=True)


def _whole_number(text: str, expected: str) -> int:
    """Return ``text`` as a whole number >= 1, or refuse it saying what was ``expected``."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f'expected {expected}, got {text!r}')
    return value


def jobs_arg(text: str) -> int:
    """Parse --jobs: a whole number of processes, at least 1."""
    return _whole_number(text, 'a whole number of processes >= 1')


def cluster_arg(text: str) -> str:
    """Parse --cluster: a Dask scheduler address, checked before any work."""
    try:
        return check_cluster_address(text)
    except ParameterError as err:
        raise argparse.ArgumentTypeError(str(err).removeprefix('--cluster ')) from err


def stride_arg(text: str) -> int:
    """Parse --stride: register one lidar scan in K, K a whole number >= 1."""
    return _whole_number(text, 'a whole number K >= 1 (one lidar scan in K is registered; 1: '
                         'every scan)')


class RoundBars:
    """Progress of a diagnosis (cli.progress.Progress): one per batch of fits of a round.

    Called as ``bars(round, done, total)``; a new one starts when the round changes or the count
    starts over (the sparse fallback's fits, after the named extensions'). A bar on a terminal,
    otherwise a line per 10 % of the batch.
    """

    def __init__(self) -> None:
        self._bar: Progress | None = None
        self._key: tuple[int, int] | None = None
        self._done = 0

    def __call__(self, round_no: int, done: int, total: int) -> None:
        if self._bar is None or self._key != (round_no, total) or done < self._done:
            self.close()
            self._bar = Progress(f'diagnose, round {round_no}', 'fits')
            self._key = (round_no, total)
        self._done = done
        self._bar(done, total)

    def close(self) -> None:
        """Close the bar in use, if any."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def default_cache_dir() -> Path:
    base = os.environ.get('XDG_CACHE_HOME') or str(Path.home() / '.cache')
    return Path(base) / 'skidkin_ros'


def add_geometry_args(parser: argparse.ArgumentParser, required: bool = False) -> None:
    group = parser.add_argument_group('robot geometry (measured)')
    group.add_argument('--wheel-radius', type=float, required=required, metavar='M',
                       help='wheel radius r in m (default: from --params, else '
                            f'{DEFAULT_GEOMETRY.wheel_radius:g})')
    group.add_argument('--track-width', type=float, required=required, metavar='M',
                       help='track width b in m (default: from --params, else '
                            f'{DEFAULT_GEOMETRY.track_width:g})')


def add_source_args(parser: argparse.ArgumentParser, ground_truth: bool = True) -> None:
    group = parser.add_argument_group(
        'reading recordings (topics are auto-detected when there is exactly one candidate)')
    group.add_argument('--wheel-topic', help='sensor_msgs/JointState topic of the wheel speeds')
    group.add_argument('--left-joints', nargs='+', metavar='JOINT',
                       help='JointState names of the left wheels (default: names with "left")')
    group.add_argument('--right-joints', nargs='+', metavar='JOINT',
                       help='JointState names of the right wheels (default: names with "right")')
    group.add_argument('--left-topic', help='std_msgs/Float64 left wheel speed topic (rad/s)')
    group.add_argument('--right-topic', help='std_msgs/Float64 right wheel speed topic (rad/s)')
    group.add_argument('--wheel-signal', choices=WHEEL_SIGNALS,
                       help='JointState: integrate the wheel velocities, the joint positions '
                       '(travel between samples) or auto (positions when they change); written '
                       'to the parameters file so the node reads the same (default velocity; '
                       "predict: the parameters file's; tables hold speeds only)")
    group.add_argument('--wheel-odometry', metavar='TOPIC',
                       help='nav_msgs/Odometry of a drive controller (diff_drive_controller): '
                       'the wheel speeds are recovered from its twist; needs '
                       '--controller-geometry')
    group.add_argument('--controller-geometry', nargs=2, type=float,
                       metavar=('RADIUS', 'SEPARATION'),
                       help="the drive controller's configured wheel_radius and "
                       'wheel_separation (m), as in its parameters (not the calibrated values)')
    group.add_argument('--controller-multipliers', nargs=3, type=float,
                       metavar=('LEFT', 'RIGHT', 'SEPARATION'),
                       help="the controller's left/right_wheel_radius_multiplier and "
                       'wheel_separation_multiplier (default 1 1 1)')
    group.add_argument('--imu-topic', help='sensor_msgs/Imu topic (optional)')
    group.add_argument('--msg-file', action='append', type=Path, metavar='PKG/msg/NAME.msg',
                       help='definition of a message type the recording does not carry (a '
                       'custom type; ROS 1 or ROS 2 .msg syntax as the recording); repeatable')
    if not ground_truth:
        return
    group.add_argument('--ground-truth', default='icp', metavar='icp|TOPIC|none',
                       help='ground truth of a bag: kiss-icp on the lidar (default), a '
                       'nav_msgs/Odometry, geometry_msgs/PoseStamped or '
                       "PoseWithCovarianceStamped topic (AMCL's amcl_pose), or none")
    group.add_argument('--lidar-topic', help='sensor_msgs/PointCloud2 topic')
    group.add_argument('--base-frame', default='base_link', help='robot body frame')
    group.add_argument('--extrinsic', nargs=6, type=float,
                       metavar=('X', 'Y', 'Z', 'ROLL', 'PITCH', 'YAW'),
                       help='lidar pose in the base frame (m, rad) when /tf_static lacks it')
    icp, chunks = IcpConfig(), ChunkOptions()
    group.add_argument('--max-range', type=float, default=icp.max_range_m, metavar='M',
                       help=f'kiss-icp maximum range (m, default {icp.max_range_m:g})')
    group.add_argument('--voxel-size', type=float, metavar='M',
                       help='kiss-icp voxel size (m, default: 6 x the point spacing of the '
                       "first cloud, kept where a self-check agrees with kiss-icp's defaults)")
    group.add_argument('--no-icp-check', action='store_true',
                       help="skip the self-check of the fast kiss-icp settings against kiss-icp's "
                       'defaults on a sample of the recording (docs/ground-truth.md)')
    group.add_argument('--stride', type=stride_arg, default=icp.stride, metavar='K',
                       help=f'register one lidar scan in K (default {icp.stride}; the '
                       'self-check compares it with every scan, docs/ground-truth.md)')
    group.add_argument('--chunk-s', type=float, default=chunks.chunk_s, metavar='S',
                       help='register the lidar in independent chunks of S seconds (default '
                       f'{chunks.chunk_s:g})')
    group.add_argument('--chunk-overlap', type=float, default=chunks.overlap_s, metavar='S',
                       help='seconds each chunk starts before its seam, to warm up and test '
                       f'the seam (default {chunks.overlap_s:g})')
    try:
        group.add_argument('--jobs', type=jobs_arg, default=usable_cpus(), metavar='N',
                           help='processes for the lidar chunks (default: every usable CPU)')
    except argparse.ArgumentError:
        pass  # the command has its own --jobs (diagnose): the same number serves both
    group.add_argument('--cluster', metavar='ADDRESS', type=cluster_arg,
                       help='run the lidar chunks on this Dask scheduler (tcp://host:8786) '
                       'instead of local processes')
    group.add_argument('--cache-dir', type=Path, default=None,
                       help=f'ICP trajectory cache (default {default_cache_dir()})')
    group.add_argument('--no-cache', action='store_true', help='always run ICP')
    group.add_argument('--no-progress', action='store_true',
                       help='no progress (bar on a terminal, else a line per 10 %%)')


def geometry_from_args(args: argparse.Namespace, fallback: Geometry | None = None) -> Geometry:
    fallback = fallback or DEFAULT_GEOMETRY
    return Geometry(args.wheel_radius if args.wheel_radius is not None
                    else fallback.wheel_radius,
                    args.track_width if args.track_width is not None else fallback.track_width)


def source_options(args: argparse.Namespace) -> SourceOptions:
    get = vars(args).get
    defaults, chunk_defaults = IcpConfig(), ChunkOptions()
    icp = IcpConfig(max_range_m=get('max_range') or defaults.max_range_m,
                    voxel_size_m=get('voxel_size'), stride=get('stride') or defaults.stride)
    chunks = ChunkOptions(chunk_s=get('chunk_s') or chunk_defaults.chunk_s,
                          overlap_s=get('chunk_overlap') or chunk_defaults.overlap_s,
                          jobs=get('jobs') or 1, cluster=get('cluster'))
    cache = None if get('no_cache') else (get('cache_dir') or default_cache_dir())
    extrinsic = get('extrinsic')
    return SourceOptions(
        wheel_topic=get('wheel_topic'), left_topic=get('left_topic'),
        right_topic=get('right_topic'),
        left_joints=tuple(get('left_joints')) if get('left_joints') else None,
        right_joints=tuple(get('right_joints')) if get('right_joints') else None,
        lidar_topic=get('lidar_topic'), imu_topic=get('imu_topic'),
        ground_truth=get('ground_truth') or 'icp', base_frame=get('base_frame') or 'base_link',
        extrinsic=extrinsic_from_xyz_rpy(extrinsic) if extrinsic else None,
        cache_dir=cache, icp=icp, chunks=chunks, icp_check=not get('no_icp_check'),
        on_progress=None if get('no_progress') else Progress('kiss-icp', 'frames'),
        wheel_signal=get('wheel_signal') or 'velocity',
        msg_files=tuple(get('msg_file') or ()),
        odometry_topic=get('wheel_odometry'), controller=controller_from_args(args))


def controller_from_args(args: argparse.Namespace) -> ControllerGeometry | None:
    """Return the drive controller's geometry given on the command line, or None."""
    get = vars(args).get
    geometry, multipliers = get('controller_geometry'), get('controller_multipliers')
    if geometry is None:
        if multipliers is not None:
            raise ConfigError('--controller-multipliers needs --controller-geometry RADIUS '
                              "SEPARATION (the controller's wheel_radius and wheel_separation)")
        return None
    left, right, separation = multipliers or (1.0, 1.0, 1.0)
    return ControllerGeometry(geometry[0], geometry[1], left, right, separation)


def check_split_without_eval(args: argparse.Namespace) -> None:
    """Refuse ``--split-by`` beside ``--eval``: the split only applies when EVAL is not given.

    With both, the evaluation data is EVAL and TRAIN is not split: the option would be ignored
    in silence (and with EVAL = TRAIN, every score would come from the training data).
    """
    if args.split_by and args.eval:
        raise ConfigError(f'--split-by {args.split_by} splits TRAIN into a training and a '
                          'held-out half when no --eval is given; with --eval the evaluation data '
                          'is EVAL and nothing is split: drop --split-by, or drop --eval to score '
                          f'the odd values of {args.split_by}')


def check_report_dir(path: Path | None, force: bool, what: str = '--report') -> None:
    """Refuse a report folder that cannot be written, or holds files without ``force``.

    Checked before any work is done (:func:`skidkin_ros.atomic.check_writable_dir`).
    """
    if path is not None:
        check_writable_dir(path, force, what)


def input_parameters(sources: Sequence[LoadedSource]) -> dict[str, Any]:
    """Node input parameters (input mode, joint names) as used when reading the recordings."""
    for source in sources:
        wheel = source.wheel_input
        if wheel.get('input') == 'joint_state':
            return {'input': 'joint_state', 'left_wheel_joints': wheel['left_wheel_joints'],
                    'right_wheel_joints': wheel['right_wheel_joints'],
                    'wheel_signal': wheel.get('wheel_signal', 'velocity')}
        if wheel.get('input') == 'wheel_topics':
            return {'input': 'wheel_topics'}
        if wheel.get('input') == 'odometry':
            return {'input': 'odometry', 'wheel_signal': 'velocity',
                    **{k: v for k, v in wheel.items() if k.startswith('controller.')}}
    return {}


def calibration_provenance(result: CalibrationResult, train: Sequence[LoadedSource],
                           evaluate: Sequence[LoadedSource], command: str) -> dict[str, Any]:
    """Return the provenance a calibration's parameters file records (sources, errors)."""
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


def plain_reference_lines(result: CalibrationResult) -> str:
    """Return the written model beside its plain window-end fit, at held-out window ends."""
    written = result.window_end.get(result.best)
    plain = result.plain_window_end
    if written is None or plain is None:
        return ''
    width = len(result.best) + 28
    lines = [f'\nheld-out ends of {written.windows} windows of {result.options.window_s:g} s '
             '(median):  position m  heading rad',
             f'  {(result.best + " (written, " + result.options.weighting + ")"):<{width}}'
             f'  {written.position_m:10.3f}  {written.yaw_rad:11.3f}',
             f'  {(result.best + " plain window-end fit"):<{width}}  {plain.position_m:10.3f}'
             f'  {plain.yaw_rad:11.3f}',
             f'  {"ratio written / plain":<{width}}  '
             f'{written.position_m / plain.position_m:9.2f}x  '
             f'{written.yaw_rad / plain.yaw_rad:10.2f}x']
    return '\n'.join(lines)


def print_calibration(result: CalibrationResult) -> None:
    """Print a calibration: segments, the error table, the fitted parameters, the warnings."""
    say(f'\nsegments: {len(result.train_segments)} training (h_t = {result.options.h_t:g} m), '
        f'{len(result.eval_segments)} evaluation (h_e = {result.options.h_e:g} m, '
        f'{result.holdout})')
    say(error_table(result.evaluation, result.fits, result.noise, result.best,
                    result.window_end, result.likelihood))
    if result.selection_rule == 'likelihood':
        say('best model: lowest held-out NLL per segment (noise fitted on the other half, by '
            'group); a model with fewer parameters is taken within 2 paired standard errors. '
            f'end yaw: median |heading error| (rad) at the end of held-out '
            f'{result.options.window_s:g} s windows; fit: {result.options.weighting} weighting')
    else:
        say('best model: eps_t and eps_theta relative to the best (a model with fewer '
            'parameters within 2 %)')
    say(plain_reference_lines(result))
    say('\nfitted parameters (± standard error):')
    for line in parameter_lines(result.fits):
        say(line)
    sym = result.fits.get('edd_symmetric')
    if sym is not None and sym.values:
        ratio = sym.values['b_hat'] / result.geometry.track_width
        say(f'  edd_symmetric b_hat / track_width = {ratio:.3f}: the '
            'wheel_separation_multiplier of diff_drive_controller that matches this data '
            f'(its alpha = {sym.values["alpha"]:.3f} would be wheel_radius_multiplier)')
    gyro = result.gyro
    if gyro is not None:
        say(f'  gyro (imu.*): scale {gyro.scale:.4f} ±{gyro.scale_se:.2g}, bias '
            f'{gyro.bias:+.5f} ±{gyro.bias_se:.2g} rad/s, time offset '
            f'{gyro.time_offset * 1e3:+.0f} ms ({gyro.pairs} pose pairs, {gyro.trimmed} trimmed '
            'as ground-truth glitches); imu.mode stays off: set it to fuse or adapt to use it')
        noise = [f'arw {gyro.arw:.2g} rad/sqrt(s)'] if math.isfinite(gyro.arw) else []
        if math.isfinite(gyro.r_floor):
            noise.append(f'adapt r_floor {gyro.r_floor:.2g} (rad/s)^2, r_rel {gyro.r_rel:.2g} '
                         f'({gyro.r_intervals} intervals)')
        if math.isfinite(gyro.adapt_yaw_scale):
            noise.append(f'yaw_noise_scale {gyro.adapt_yaw_scale:.2g} ({gyro.scale_windows} '
                         'held-out windows)')
        if noise:
            say(f"  gyro modes' noise (imu.*): {', '.join(noise)}")
    for warning in result.warnings:
        say(f'  warning: {warning}')
