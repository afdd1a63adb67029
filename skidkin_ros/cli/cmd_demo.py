"""``skidkin demo``: the whole pipeline on a built-in default, in a few minutes.

1. simulate a training drive and four evaluation drives (wheels, 16-ring lidar, IMU) as rosbag2;
2. calibrate all five models on the training bag with kiss-icp ground truth, scored on the
   evaluation bags; write the parameters file and the report;
3. for reference, fit the same models on the exact simulated trajectory;
4. replay the evaluation drive's wheel speeds through the real odom_node (rclpy, DDS) loaded
   with the written parameters file, and report its error against the true trajectory and its
   agreement with ``skidkin predict``.

The demo drives as much as the calibrator's checks need, so that a first run warns about nothing
it did not earn: the held-out likelihood that picks the model needs two drives or more, and the
covariance check wants at least 30 held-out segments at every horizon up to 4 m (three drives of
120 s gave 25 of 4 m, four give about 33).
"""

from __future__ import annotations

import argparse
from pathlib import Path
import shutil
import time

import numpy as np

from skidkin_ros.adapters.sim_writer import write_bag
from skidkin_ros.adapters.sources import load_source, SourceOptions
from skidkin_ros.atomic import check_writable_dir
from skidkin_ros.cli.common import (calibration_provenance, default_cache_dir,
                                    input_parameters, print_calibration, say)
from skidkin_ros.cli.progress import Progress
from skidkin_ros.core.calibration.evaluation import ErrorStats, relative_pose_errors
from skidkin_ros.core.calibration.pipeline import (calibrate, calibrate_interval,
                                                   CalibrationOptions, result_to_parameters)
from skidkin_ros.core.odometry.config import OdometryConfig, write_params_file
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.errors import OutputError
from skidkin_ros.sim.simulate import SimConfig, simulate

__all__ = ['add_parser', 'pipeline', 'DEMO_TRAIN', 'DEMO_EVAL']

DEMO_TRAIN = SimConfig(duration_s=180.0, seed=11)
DEMO_EVAL = SimConfig(duration_s=120.0, seed=12)
DEMO_EVAL_DRIVES = 4  # seeds 12 to 15


def _stats_line(label: str, eps_t: np.ndarray, eps_th: np.ndarray) -> str:
    t, th = ErrorStats.of(eps_t), ErrorStats.of(eps_th)
    return (f'{label:<34} eps_t {t.median:.4f} m/m [{t.q25:.4f}, {t.q75:.4f}]   '
            f'eps_theta {th.median:.3f} deg/m [{th.q25:.3f}, {th.q75:.3f}]   ({t.count} segs)')


# What the demo writes in its folder: the only entries --force removes.
def _eval_name(index: int) -> str:
    return 'eval_bag' if index == 0 else f'eval_bag_{index + 1}'


DEMO_ENTRIES = ('train_bag', 'train_bag_truth.csv', 'params.yaml', 'report') + tuple(
    name for i in range(9) for name in (_eval_name(i), f'{_eval_name(i)}_truth.csv'))


def _prepare(out: Path, force: bool) -> None:
    """Make the output folder; with ``force`` remove an earlier demo's outputs, and only them."""
    check_writable_dir(out, force, '--out')
    if out.is_dir():
        strangers = sorted(p.name for p in out.iterdir() if p.name not in DEMO_ENTRIES)
        if strangers:
            raise OutputError(f'{out} holds files the demo did not write ({strangers[:5]}); '
                              'refusing to delete them: choose another --out')
        for name in DEMO_ENTRIES:
            entry = out / name
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            elif entry.exists() or entry.is_symlink():
                entry.unlink()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f'cannot create {out}: {err}') from err


def run(args: argparse.Namespace) -> int:
    pipeline(args)
    return 0


def pipeline(args: argparse.Namespace) -> dict:
    """Run the demo, print its progress and return its numbers (for tests and docs/results.md)."""
    started = time.monotonic()
    out: Path = args.out
    _prepare(out, args.force)
    count = getattr(args, 'eval_drives', DEMO_EVAL_DRIVES)
    train_cfg = SimConfig(duration_s=args.train_duration, seed=DEMO_TRAIN.seed)
    eval_cfgs = [SimConfig(duration_s=args.eval_duration, seed=DEMO_EVAL.seed + i)
                 for i in range(count)]
    geometry = train_cfg.geometry
    say(f'[1/4] simulating {train_cfg.duration_s:g} s (training) and {count} x '
        f'{args.eval_duration:g} s (evaluation) of skid-steer driving; true model '
        f'{train_cfg.true_model} {dict(train_cfg.true_params)}')
    train_sim = simulate(train_cfg)
    eval_sims = [simulate(cfg) for cfg in eval_cfgs]
    eval_sim = eval_sims[0]  # replayed through the node in step 4
    train_bag, train_csv = write_bag(train_sim, out / 'train_bag', storage='sqlite3')
    eval_bags = [write_bag(sim, out / _eval_name(i), storage='mcap')[0]
                 for i, sim in enumerate(eval_sims)]

    say('[2/4] calibrating with kiss-icp ground truth (skidkin calibrate)')
    cache = None if args.no_cache else default_cache_dir()
    opts = SourceOptions(cache_dir=cache,
                         on_progress=Progress('kiss-icp', 'frames') if args.progress else None)
    train_src = load_source(train_bag, opts)
    eval_srcs = [load_source(bag, opts) for bag in eval_bags]
    for src in (train_src, *eval_srcs):
        say(f'      {src.path.name}: {src.truth_info.get("ground_truth")}, frames '
            f'{src.truth_info.get("frames")}')
    eval_drives = [drive for src in eval_srcs for drive in src.drives]
    options = CalibrationOptions(seed=0)
    result = calibrate_interval(train_src.drives, eval_drives, geometry, options)
    print_calibration(result)
    say(f'      sample interval: {result.options.interval} (chosen on the evaluation drives)')
    params = out / 'params.yaml'
    flat = result_to_parameters(result, {'robot': 'demo_sim_husky',
                                         **input_parameters([train_src])})
    prov = calibration_provenance(result, [train_src], eval_srcs, 'skidkin demo')
    write_params_file(params, flat, prov)
    from skidkin_ros.report.page import write_report  # matplotlib: only here

    page = write_report(result, out / 'report', force=True)
    say(f'      parameters file: {params}\n      report: {page}')

    say('[3/4] reference: the same models fitted on the exact simulated trajectory')
    exact = calibrate([train_sim.drive('train_exact')],
                      [sim.drive(f'eval_exact_{i}') for i, sim in enumerate(eval_sims)],
                      geometry, result.options)
    truth_params = dict(train_cfg.true_params)
    listed = ', '.join(f'{k}={v:g}' for k, v in truth_params.items())
    say(f'      true {train_cfg.true_model}: {listed}')
    for label, res in (('fitted on kiss-icp', result), ('fitted on exact truth', exact)):
        fit = res.fits[train_cfg.true_model]
        say(f'      {label:<22} ' + ', '.join(f'{k}={v:.4f}' for k, v in fit.values.items()))
    best = result.best
    ev_icp, ev_exact = result.evaluation[best], exact.evaluation[best]
    say(f'      {best} on the evaluation drives: eps_t {ev_icp.stats_t.median:.4f} m/m '
        f'(icp) vs {ev_exact.stats_t.median:.4f} (exact); eps_theta '
        f'{ev_icp.stats_theta.median:.3f} deg/m (icp) vs {ev_exact.stats_theta.median:.3f} '
        '(exact)')

    say('[4/4] replaying the evaluation drive through the real odom_node (rclpy + DDS) loaded '
        f'with {params.name}')
    from skidkin_ros.node.replay import replay_through_node  # rclpy only when needed

    wheels = eval_srcs[0].drives[0].wheels
    replay = replay_through_node(wheels, params_file=params)
    config = OdometryConfig.from_file(params)
    offline = Odometer.from_config(config).predict(wheels)
    index = {int(t): i for i, t in enumerate(offline.t_ns)}
    rows = np.array([index[int(t)] for t in replay.t_ns])
    diff = np.abs(replay.poses - offline.poses[rows]).max()
    cov_diff = np.abs(replay.pose_cov - offline.pose_covariances[rows]).max()
    say(f'      node published {len(replay)} odometry messages; max |node - skidkin predict| '
        f'= {diff:.2e} (m, rad), pose covariance {cov_diff:.2e}')
    truth = eval_sim.truth
    say(_stats_line(f'node ({config.model}) vs truth', *relative_pose_errors(
        replay.t_ns, replay.poses, truth)))
    ideal = Odometer.from_config(config, model='ideal_dd').predict(wheels)
    say(_stats_line('ideal diff-drive vs truth', *relative_pose_errors(
        ideal.t_ns, ideal.poses, truth)))
    say(f'done in {time.monotonic() - started:.0f} s; outputs in {out}/')
    return {'params': params, 'best': best, 'true_params': truth_params,
            'fitted_icp': dict(result.fits[train_cfg.true_model].values),
            'fitted_exact': dict(exact.fits[train_cfg.true_model].values),
            'eval_icp': ev_icp, 'eval_exact': ev_exact, 'node_vs_predict': float(diff),
            'node_vs_predict_covariance': float(cov_diff),
            'node_eps': relative_pose_errors(replay.t_ns, replay.poses, truth),
            'ideal_eps': relative_pose_errors(ideal.t_ns, ideal.poses, truth)}


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        'demo', help='simulate, calibrate with kiss-icp, replay through the node (minutes)',
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--out', type=Path, default=Path('demo_out'), help='output folder')
    parser.add_argument('--force', action='store_true', help='replace an existing output folder')
    parser.add_argument('--train-duration', type=float, default=DEMO_TRAIN.duration_s,
                        metavar='S')
    parser.add_argument('--eval-duration', type=float, default=DEMO_EVAL.duration_s,
                        metavar='S', help='length of each evaluation drive')
    parser.add_argument('--eval-drives', type=int, default=DEMO_EVAL_DRIVES, metavar='N',
                        choices=range(1, 10), help='evaluation drives (1-9; the held-out '
                        'likelihood that picks the model needs 2 or more)')
    parser.add_argument('--no-cache', action='store_true', help='always run ICP')
    parser.add_argument('--progress', action='store_true', help='show ICP progress bars')
    parser.set_defaults(run=run)
