"""``skidkin groundtruth``: the lidar (kiss-icp) trajectory of base_link, as CSV and TUM."""

from __future__ import annotations

import argparse
import dataclasses
import io
from pathlib import Path

import numpy as np

from skidkin_ros.adapters.sources import load_source
from skidkin_ros.atomic import atomic_write_text, check_writable
from skidkin_ros.cli.common import add_source_args, print_notes, say, source_options
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.errors import ConfigError

__all__ = ['add_parser', 'track_csv', 'track_tum']

_NO_GEOMETRY = ('--wheel-radius', '--track-width')


def track_csv(track: PoseTrack) -> str:
    out = io.StringIO()
    out.write('t,t_ns,x,y,yaw,valid\n')
    t0 = track.t_ns[0] if len(track) else 0
    for t_ns, x, y, yaw, ok in zip(track.t_ns, track.x, track.y, track.yaw, track.valid):
        out.write(f'{(t_ns - t0) * 1e-9:.9f},{t_ns},{x:.6f},{y:.6f},{yaw:.6f},{int(ok)}\n')
    return out.getvalue()


def track_tum(track: PoseTrack) -> str:
    """TUM format (evo): stamp x y z qx qy qz qw, stamps in seconds."""
    lines = []
    for t_ns, x, y, yaw in zip(track.t_ns, track.x, track.y, track.yaw):
        lines.append(f'{t_ns * 1e-9:.9f} {x:.6f} {y:.6f} 0 0 0 {np.sin(yaw / 2):.9f} '
                     f'{np.cos(yaw / 2):.9f}')
    return '\n'.join(lines) + '\n'


def run(args: argparse.Namespace) -> int:
    given = [name for name in _NO_GEOMETRY if getattr(args, name[2:].replace('-', '_'))]
    if given:
        raise ConfigError(f'skidkin groundtruth takes no robot geometry ({", ".join(given)}): '
                          "the ground truth's wheel check scales the wheels against ICP itself; "
                          'drop the option (calibrate and predict take it)')
    check_writable(args.out, args.force)
    if args.tum:
        check_writable(args.tum, args.force)
    # The wheels are only a gross check of the ground truth: a bag without them is read.
    options = dataclasses.replace(source_options(args), wheels_optional=True)
    loaded = load_source(args.bag, options, need_truth=True)
    print_notes([loaded])
    track = loaded.drives[0].truth
    atomic_write_text(args.out, track_csv(track), force=args.force)
    if args.tum:
        atomic_write_text(args.tum, track_tum(track), force=args.force)
    length = float(track.path_length()[-1]) if len(track) else 0.0
    say(f'{loaded.truth_info.get("ground_truth")}: {len(track)} poses, '
        f'{int(np.count_nonzero(~track.valid))} flagged invalid, {length:.1f} m of path')
    say(f'wrote {args.out}' + (f' and {args.tum} (TUM)' if args.tum else ''))
    return 0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        'groundtruth', help='lidar ground truth of a bag with kiss-icp (CSV, TUM for evo)',
        description='Run kiss-icp over the lidar of a rosbag2 or ROS 1 bag (deskewed with\n'
        'the per-point times), convert the poses to base_link with the extrinsic, and write\n'
        'the planar trajectory. The recording is registered in independent chunks on --jobs\n'
        'processes (or on a Dask cluster with --cluster), each chunk cached as it finishes:\n'
        'a later calibrate of the same bag, or an interrupted run, skips what is done. Poses\n'
        "are judged by the registration's own quality, the IMU's yaw rate and, for gross\n"
        'errors only, the wheels (a bag without wheel topics is read, that check\n'
        'skipped); no robot geometry is needed.',
        epilog='examples:\n  skidkin groundtruth drive_bag --out traj.csv --tum traj_tum.txt\n'
        '  skidkin groundtruth drive_bag --out traj.csv --jobs 4 --chunk-s 60\n'
        '  skidkin groundtruth drive_bag --out traj.csv --cluster tcp://10.0.0.5:8786',
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('bag', type=Path,
                        help='rosbag2 folder or .db3/.mcap file, or a ROS 1 .bag')
    parser.add_argument('--out', type=Path, required=True, help='trajectory CSV to write')
    parser.add_argument('--tum', type=Path, help='also write the TUM format (for evo)')
    parser.add_argument('--force', action='store_true', help='overwrite existing outputs')
    add_source_args(parser)
    # Not options of this command; kept out of --help, and refused with the reason if given.
    for name in _NO_GEOMETRY:
        parser.add_argument(name, help=argparse.SUPPRESS)
    parser.set_defaults(run=run)
