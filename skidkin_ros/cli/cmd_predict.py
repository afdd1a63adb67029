"""``skidkin predict``: a model's odometry for a recording, through the node's own integrator."""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
from pathlib import Path

import numpy as np
from skidkin_ros.adapters.bag_reader import open_recording
from skidkin_ros.adapters.sources import is_table, load_source, SourceOptions
from skidkin_ros.atomic import atomic_write_text, check_writable
from skidkin_ros.cli.common import add_source_args, print_notes, say, source_options
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.core.odometry.config import (check_model_given, default_parameters_warning,
                                              OdometryConfig)
from skidkin_ros.core.odometry.controller import ControllerGeometry
from skidkin_ros.core.odometry.gyro_params import GYRO_MODES
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.core.online import online_odometer
from skidkin_ros.errors import DataError, ParameterError

__all__ = ['add_parser']


def _reading(args: argparse.Namespace, config: OdometryConfig) -> SourceOptions:
    """Return how to read the recording: with the node's wheel limits, pairing and signal."""
    given = getattr(args, 'wheel_signal', None)
    if given is not None and given != config['wheel_signal']:
        raise ParameterError(f'--wheel-signal {given} differs from the wheel_signal of the '
                             f'parameters file, {config["wheel_signal"]}, which the node uses; '
                             'drop the option (predict reads what the node reads)')
    options = source_options(args)
    controller = None
    if config['input'] == 'odometry':
        controller = ControllerGeometry.from_values(config.values)
        if options.controller is not None and options.controller != controller:
            raise ParameterError(
                f'--controller-geometry/--controller-multipliers ({options.controller}) differ '
                f'from the controller.* of the parameters file ({controller}), which the node '
                'uses; drop the options (predict reads what the node reads)')
    elif options.controller is not None or options.odometry_topic is not None:
        raise ParameterError(
            f'the parameters file has input {config["input"]}, not odometry: the node would not '
            "read a controller's odometry; calibrate from the odometry (--wheel-odometry) "
            'first, or drop --wheel-odometry / --controller-geometry')
    return dataclasses.replace(options, controller=controller,
                               max_wheel_speed_rad_s=config['max_wheel_speed'],
                               pair_tolerance_s=config['pair_tolerance'],
                               max_wheel_acceleration=config['max_wheel_acceleration'],
                               max_dt_s=config['max_dt'], wheel_signal=config['wheel_signal'])


def _check_gyro(config: OdometryConfig, drives) -> None:
    if config.imu.mode != 'off' and all(drive.imu is None for drive in drives):
        raise DataError(f'imu mode {config.imu.mode} needs gyro samples and the recording has '
                        'none: a table needs the imu_yaw_rate column, a bag a sensor_msgs/Imu '
                        'topic (--imu-topic); or use --imu-mode off')


def _predict_table(args: argparse.Namespace, config: OdometryConfig) -> tuple[str, int]:
    loaded = load_source(args.source, _reading(args, config), need_truth=True)
    print_notes([loaded])
    _check_gyro(config, loaded.drives)
    with args.source.open(newline='', encoding='utf-8-sig') as handle:
        rows = list(csv.reader(handle))
    header, body = rows[0], rows[1:]
    extra = [['', '', ''] for _ in body]
    odometer = Odometer.from_config(config)
    for drive in loaded.drives:
        pred = odometer.predict(drive.wheels, start=drive.truth.poses[0], imu=drive.imu)
        for row, pose in zip(drive.meta['row_index'], pred.poses):
            extra[row] = [f'{pose[0]:.6f}', f'{pose[1]:.6f}', f'{pose[2]:.6f}']
    out = io.StringIO()
    writer = csv.writer(out, lineterminator='\n')
    writer.writerow(header + ['pred_x', 'pred_y', 'pred_yaw'])
    for row, more in zip(body, extra):
        writer.writerow(row + more)
    return out.getvalue(), len(body)


def _predict_bag(args: argparse.Namespace, config: OdometryConfig) -> tuple[str, int]:
    reading = _reading(args, config)
    if args.reference is not None:
        reading = dataclasses.replace(reading, ground_truth=args.reference)
    loaded = load_source(args.source, reading, need_truth=args.reference is not None)
    print_notes([loaded])
    _check_gyro(config, loaded.drives)
    drive = loaded.drives[0]
    wheels = drive.wheels
    reference, refused = drive.truth, 0
    if args.reference is not None:
        reference, refused, config = _frames_checked(args.source, args.reference, reference,
                                                     config)
    odometer = online_odometer(config)
    odometer.counters['reference_frame'] += refused
    # The reader applied the wheel-jump rule as the node does (encoder travel exempt).
    pred = odometer.predict(wheels, imu=drive.imu, reference=reference
                            if args.reference is not None else None,
                            jumps_dropped=config['wheel_signal'] != 'velocity')
    if odometer.learner is not None:
        summary = odometer.learner.summary()
        say(f'online calibration: {int(summary["grounds"])} ground(s), '
            f'{odometer.counters["online_segments"]} segments, last state {summary["state"]}; '
            + ', '.join(f'{name} {value:.4g}' for name, value in odometer.learner.values.items()))
    out = io.StringIO()
    out.write('t,t_ns,x,y,yaw,vx,vy,wz,status,cov_xx,cov_xy,cov_xyaw,cov_yy,cov_yyaw,'
              'cov_yawyaw\n')
    t0 = int(wheels.t_ns[0])
    for t_ns, pose, twist, status, cov in zip(pred.t_ns, pred.poses, pred.twists, pred.status,
                                              pred.pose_covariances):
        # the planar block of the published 6 x 6 (x, y, yaw), full precision (repr)
        block = (cov[0, 0], cov[0, 1], cov[0, 5], cov[1, 1], cov[1, 5], cov[5, 5])
        out.write(f'{(int(t_ns) - t0) * 1e-9:.9f},{int(t_ns)},{pose[0]:.9f},{pose[1]:.9f},'
                  f'{pose[2]:.9f},{twist[0]:.9f},{twist[1]:.9f},{twist[2]:.9f},'
                  f'{status.value},' + ','.join(repr(float(v)) for v in block) + '\n')
    return out.getvalue(), len(wheels)


def _frames_checked(source: str, topic: str, track: PoseTrack, config: OdometryConfig
                    ) -> tuple[PoseTrack, int, OdometryConfig]:
    """Apply online.reference_frame_id / reference_child_frame_id as the node does.

    The pose track carries no frames: the poses in other frames are dropped here (the node
    refuses them on arrival, which changes nothing else), and the configuration handed to the
    odometer keeps no frame rule (every pose left matches it). Returns the track, the poses
    refused and that configuration.
    """
    online = config.online
    if not (online.reference_frame_id or online.reference_child_frame_id):
        return track, 0, config
    with open_recording(source) as recording:
        frames = recording.read_pose_frames(topic)
    other = [t for t, frame, child in frames if not online.frames_match(frame, child)]
    if len(other) == len(frames):
        seen = sorted({f'{frame!r}/{child!r}' for _, frame, child in frames})[:3]
        say(f'online calibration: no pose on {topic} is in the configured frames '
            f'(online.reference_frame_id {online.reference_frame_id!r}, '
            f'reference_child_frame_id {online.reference_child_frame_id!r}); the topic has '
            f'frame_id/child_frame_id {", ".join(seen)}: nothing can be learned (fix the '
            'parameters file, or leave them empty to take any frame)')
    keep = ~np.isin(track.t_ns, np.array(other, dtype=np.int64))
    kept = PoseTrack(track.t_ns[keep], track.x[keep], track.y[keep], track.yaw[keep],
                     track.valid[keep])
    anyframe = OdometryConfig.from_flat({**config.values, 'online.reference_frame_id': '',
                                         'online.reference_child_frame_id': ''})
    return kept, int(np.count_nonzero(~keep)), anyframe


def run(args: argparse.Namespace) -> int:
    check_writable(args.out, args.force)
    overrides = {'use_parameter_covariance': False} if args.no_parameter_covariance else {}
    if args.reference is not None:
        if is_table(args.source):
            raise ParameterError('--reference needs a bag (a nav_msgs/Odometry topic in it); a '
                                 'trajectory table is predicted segment by segment from its '
                                 'ground truth')
        overrides['online.enabled'] = True
    config = OdometryConfig.from_file(args.params, args.model, overrides or None)
    if args.model is not None:
        check_model_given(args.model, config.held_models, f'the file {args.params}',
                          config.augmented_base)
    else:
        # the file's own model: run as the node runs it, with the node's warning
        warning = default_parameters_warning(config.model, config.held_models,
                                             config.augmented_base)
        if warning is not None:
            say(f'warning: {args.params}: {warning}')
    if args.imu_mode is not None:
        config = dataclasses.replace(config, values={**config.values, 'imu.mode': args.imu_mode})
    if config.imu.mode != 'off':
        say(f'imu mode {config.imu.mode}: the gyro is used as the node uses it')
    text, rows = (_predict_table if is_table(args.source) else _predict_bag)(args, config)
    atomic_write_text(args.out, text, force=args.force)
    say(f'{config.model}: predicted {rows} samples -> {args.out}')
    return 0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        'predict', help="a model's odometry at every wheel sample (the node's integrator)",
        description='Integrate the wheel speeds of a recording with a calibrated model, exactly '
        'as odom_node does. For a trajectory table: the same rows plus pred_x, pred_y, pred_yaw, '
        'each segment started at its ground-truth start pose. For a bag: t, x, y, yaw (and the '
        'twist and the published pose covariance) at every wheel sample, starting at the origin '
        'like the node.')
    parser.add_argument('source', type=Path, help='bag or trajectory table')
    parser.add_argument('--params', type=Path, required=True, help='parameters file')
    parser.add_argument('--model', help="model to use (default: the file's model)")
    parser.add_argument('--imu-mode', choices=GYRO_MODES,
                        help="use the gyro as odom_node's imu.mode does (default: the file's "
                        'imu.mode); a bag needs --imu-topic (or one Imu topic), a table the '
                        'imu_yaw_rate column')
    parser.add_argument('--reference', metavar='TOPIC',
                        help="a bag's nav_msgs/Odometry (or PoseStamped) topic to learn the "
                        'parameters from online, as odom_node does with online.enabled and '
                        'reference/odom remapped to TOPIC (the online.* parameters of --params '
                        'apply)')
    parser.add_argument('--out', type=Path, required=True, help='CSV to write')
    parser.add_argument('--force', action='store_true', help='overwrite an existing output')
    parser.add_argument('--no-parameter-covariance', action='store_true',
                        help="leave the calibration's own uncertainty out of the covariance "
                        '(as the node with use_parameter_covariance: false)')
    add_source_args(parser, ground_truth=False)
    parser.set_defaults(run=run)
