"""``skidkin simulate``: a simulated skid-steer drive written as a rosbag2 (+ its true path)."""

from __future__ import annotations

import argparse
from pathlib import Path

from skidkin_ros.adapters.sim_writer import write_bag
from skidkin_ros.atomic import check_writable, check_writable_dir
from skidkin_ros.cli.common import say
from skidkin_ros.core.kinematics.specs import DEFAULT_GEOMETRY
from skidkin_ros.errors import OutputError, ParameterError
from skidkin_ros.sim.effects import EFFECTS, make_effect
from skidkin_ros.sim.simulate import SimConfig, simulate

__all__ = ['add_parser']


def _effects(items: list[str] | None) -> tuple:
    effects = []
    for item in items or []:
        name, _, strength = item.partition('=')
        if name not in EFFECTS:
            raise ParameterError(f'unknown effect {name!r}; known: {", ".join(EFFECTS)}')
        effects.append(make_effect(name, float(strength) if strength else None))
    return tuple(effects)


def run(args: argparse.Namespace) -> int:
    truth_csv = args.truth or Path(str(args.out).rstrip('/') + '_truth.csv')
    check_writable(truth_csv, args.force, '--truth')  # before the simulation, not after it
    if args.out.exists() and not args.force:
        raise OutputError(f'{args.out} already exists; pass --force to replace it')
    check_writable_dir(args.out.parent if str(args.out.parent) else Path('.'), True, '--out')
    config = SimConfig(duration_s=args.duration, seed=args.seed, wheel_radius=args.wheel_radius,
                       track_width=args.track_width, effects=_effects(args.effect),
                       encoder_noise_rad_s=args.encoder_noise)
    sim = simulate(config)
    bag, csv = write_bag(sim, args.out, storage=args.storage, overwrite=args.force,
                         truth_csv=truth_csv)
    say(f'simulated {args.duration:g} s of driving (seed {args.seed}, true model '
        f'{config.true_model} {dict(config.true_params)}, effects '
        f'{[e.as_dict() for e in config.effects] or "none"})')
    say(f'bag: {bag} ({args.storage})   true trajectory: {csv}')
    return 0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        'simulate', help='write a simulated drive (wheels, 3D lidar, IMU, tf_static) as rosbag2',
        description='Simulate a skid-steer robot driven over its wheel-speed input space, with a '
        'ray-cast 16-ring lidar with per-point times and motion distortion, and write it as a '
        'rosbag2 plus the true trajectory as a CSV table.')
    parser.add_argument('--out', type=Path, required=True, help='bag folder to create')
    parser.add_argument('--duration', type=float, default=120.0, help='seconds of driving')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--wheel-radius', type=float, default=DEFAULT_GEOMETRY.wheel_radius,
                        metavar='M')
    parser.add_argument('--track-width', type=float, default=DEFAULT_GEOMETRY.track_width,
                        metavar='M')
    parser.add_argument('--encoder-noise', type=float, default=0.05, metavar='RAD_S')
    parser.add_argument('--effect', action='append', metavar='NAME[=STRENGTH]',
                        help='add an unmodelled effect (repeatable): ' + ', '.join(EFFECTS))
    parser.add_argument('--storage', choices=('sqlite3', 'mcap'), default='sqlite3')
    parser.add_argument('--truth', type=Path, help='true trajectory CSV (default OUT_truth.csv)')
    parser.add_argument('--force', action='store_true', help='overwrite existing outputs')
    parser.set_defaults(run=run)
