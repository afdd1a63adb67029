"""Where the CPU of one registration goes, stage by stage: the ground truth's loop vs kiss-icp's.

One scene's bag (default: the courtyard, 60 s) is registered over its whole length, in this
process, on one thread, twice:

* ``ours``: what a chunk of ``skidkin groundtruth`` does per frame (``register_frames``), with
  the settings it would choose there (on the courtyard: kiss-icp's defaults, voxel 1 m);
* ``kiss``: what ``kiss_icp_pipeline`` does per frame (its rosbag reader, ``read_point_cloud``,
  ``KissICP.register_frame``, kiss-icp's defaults), on one thread (``--kiss-threads 0`` for
  its default, every core).

Each stage is timed on the CPU clock (``time.process_time``, no profiler), calling kiss-icp's
C++ parts through its pybind module so that the numpy -> C++ point conversions are timed on
their own:

decode
    reading the bag and decoding the PointCloud2 (ours: ``iter_lidar``; kiss: rosbags'
    deserialiser and ``read_point_cloud``);
prepare
    our checks of the cloud (finite, range, point times);
convert
    numpy -> ``std::vector<Eigen::Vector3d>`` (kiss-icp's ``_Vector3dVector``), all calls;
preprocess
    kiss-icp's range crop and deskew (C++);
voxelize
    the two voxel grids (C++: 0.5 and 1.5 voxel);
align
    the ICP against the local map (C++: the nearest-neighbour search in the voxel hash map
    and the Gauss-Newton steps);
map
    the local map's update (C++: add the frame, drop the far points);
quality
    our per-frame quality measure (a cKDTree of the map points and a query of 400 points);
rest
    everything else in the loop (poses, threshold, Python).

Variants (``--variant LABEL=key=value,...``) register again with changed settings
(``max_points_per_voxel``, ``max_range_m``, ``deskew``, ``convergence``, ``voxel_size_m``)
and report the 1 s increment error against the simulator's truth, so that a cheaper setting is
seen with what it costs in accuracy:

``--old DIR`` times the whole ``register_frames`` of another checkout (a ``git archive`` of an
older commit) against this one in fresh interpreters, alternated ``--rounds`` times;
``--threads-ab R`` times kiss-icp's loop with one thread and with every core, alternated:

    python lab/bench/gt_stages.py --scene courtyard --duration 60
    python lab/bench/gt_stages.py --variant mpv10=max_points_per_voxel=10 --seed 13
    python lab/bench/gt_stages.py --old /tmp/old --rounds 5 --threads-ab 3
"""

from __future__ import annotations

import argparse
from dataclasses import replace
import json
from pathlib import Path
import sys
import tempfile
import time
from typing import Any, Sequence

import gt_bench
import gt_scenes
import numpy as np

STAGES = ('decode', 'prepare', 'convert', 'preprocess', 'voxelize', 'align', 'map', 'quality',
          'rest')


class _Clock:
    """CPU seconds per stage."""

    def __init__(self) -> None:
        self.spent = dict.fromkeys(STAGES, 0.0)
        self.mark = time.process_time()

    def lap(self, stage: str) -> None:
        now = time.process_time()
        self.spent[stage] += now - self.mark
        self.mark = now


def _frames_ours(bag: Path, topic: str, clock: _Clock) -> Any:
    from skidkin_ros.adapters.bag_reader import open_recording

    with open_recording(str(bag)) as rec:
        for frame in rec.iter_lidar(topic):
            clock.lap('decode')
            yield frame
            clock.mark = time.process_time()


def ours(bag: Path, topic: str, config: Any, new_loop: bool = True
         ) -> tuple[dict[str, float], list[int], np.ndarray]:
    """Register like ``register_frames`` (same arithmetic), timing each stage.

    ``new_loop`` False: the loop as it was before (two logarithms per frame, a balanced
    cKDTree for the quality measure), for a before/after in one run.

    Returns (CPU s per stage, pose stamps ns, poses 4x4 of the lidar).
    """
    from kiss_icp.kiss_icp import KissICP
    from kiss_icp.pybind import kiss_icp_pybind as kp
    from scipy.spatial import cKDTree

    from skidkin_ros.adapters.lidar_quality import _world, registration_quality
    from skidkin_ros.adapters.lidar_register import _prepare, _TREE
    from skidkin_ros.core.rigid import se3_exp_scaled, se3_log, se3_power

    clock = _Clock()
    kiss = None
    last_end = None
    last_dt = 0
    reference = None
    stamps, poses = [], []
    for index, frame in enumerate(_frames_ours(bag, topic, clock)):
        end = int(frame.end_ns)
        code, points, times, stamp, spread_ns = _prepare(frame, index, config)
        clock.lap('prepare')
        if points is None:
            continue
        if kiss is None:
            config = config.with_voxel_for(points)
            kiss = KissICP(config.kiss_config())
        dt_ns = end - last_end if last_end is not None else 0
        delta = kiss.last_delta
        if new_loop and last_dt > 0 and dt_ns > 0:
            twist = se3_log(delta)
            guess_delta = se3_exp_scaled(*twist, dt_ns / last_dt)
            sweep_delta = se3_exp_scaled(*twist, min(spread_ns, dt_ns) / last_dt)
        elif last_dt > 0 and dt_ns > 0:
            guess_delta = se3_power(delta, dt_ns / last_dt)
            sweep_delta = se3_power(delta, min(spread_ns, dt_ns) / last_dt)
        else:
            guess_delta = sweep_delta = delta
        clock.lap('rest')
        pts = kp._Vector3dVector(points)
        clock.lap('convert')
        frame_v = kiss.preprocessor._preprocessor._preprocess(pts, times.ravel(), sweep_delta)
        clock.lap('preprocess')
        down_v = kp._voxel_down_sample(frame_v, config.voxel_size * 0.5)
        source_v = kp._voxel_down_sample(down_v, config.voxel_size * 1.5)
        clock.lap('voxelize')
        source = np.asarray(source_v)
        frame_downsample = np.asarray(down_v)
        clock.lap('convert')
        sigma = kiss.adaptive_threshold.get_threshold()
        initial_guess = kiss.last_pose @ guess_delta
        clock.lap('rest')
        _align_and_map(kiss, clock, source_v, down_v, initial_guess, sigma)
        last_dt = dt_ns if dt_ns > 0 else last_dt
        pose = kiss.last_pose.copy()
        clock.lap('rest')
        if reference is not None:
            registration_quality(source, pose, reference, config.voxel_size,
                                 config.quality_points)
        reference = (cKDTree(_world(frame_downsample, pose), **_TREE) if new_loop
                     else cKDTree(_world(frame_downsample, pose)))
        clock.lap('quality')
        last_end = end
        stamps.append(stamp)
        poses.append(pose)
    return clock.spent, stamps, np.array(poses)


def _align_and_map(kiss, clock, source_v, down_v, initial_guess, sigma) -> None:
    """KissICP.register_frame's steps after voxelizing (align, threshold, map), per stage."""
    new_pose = kiss.registration._registration._align_points_to_map(
        points=source_v, voxel_map=kiss.local_map._internal_map,
        initial_guess=initial_guess, max_correspondance_distance=3 * sigma, kernel=sigma)
    clock.lap('align')
    kiss.adaptive_threshold.update_model_deviation(np.linalg.inv(initial_guess) @ new_pose)
    clock.lap('rest')
    kiss.local_map._internal_map._update(down_v, new_pose)
    clock.lap('map')
    kiss.last_delta = np.linalg.inv(kiss.last_pose) @ new_pose
    kiss.last_pose = new_pose


def kiss_pipeline(bag: Path, topic: str, threads: int) -> tuple[dict[str, float], int]:
    """Register like ``kiss_icp_pipeline`` (its reader, its register_frame), per stage."""
    from kiss_icp.config import load_config
    from kiss_icp.datasets.rosbag import RosbagDataset
    from kiss_icp.kiss_icp import KissICP
    from kiss_icp.pybind import kiss_icp_pybind as kp

    clock = _Clock()
    dataset = RosbagDataset(bag, topic=topic)
    config = load_config(None)
    config.registration.max_num_threads = threads
    kiss = KissICP(config)
    voxel = config.mapping.voxel_size
    clock.lap('rest')
    for idx in range(len(dataset)):
        points, timestamps = dataset[idx]
        clock.lap('decode')
        pts = kp._Vector3dVector(points)
        clock.lap('convert')
        frame_v = kiss.preprocessor._preprocessor._preprocess(
            pts, timestamps.ravel(), kiss.last_delta)
        clock.lap('preprocess')
        down_v = kp._voxel_down_sample(frame_v, voxel * 0.5)
        source_v = kp._voxel_down_sample(down_v, voxel * 1.5)
        clock.lap('voxelize')
        # what KissICP.voxelize hands back to Python, and what the calls convert again
        np.asarray(source_v), np.asarray(down_v)
        clock.lap('convert')
        sigma = kiss.adaptive_threshold.get_threshold()
        initial_guess = kiss.last_pose @ kiss.last_delta
        clock.lap('rest')
        _align_and_map(kiss, clock, source_v, down_v, initial_guess, sigma)
        clock.lap('rest')
    return clock.spent, len(dataset)


def threads_ab(bag: Path, topic: str, rounds: int) -> dict[str, list[float]]:
    """Wall and CPU s of kiss-icp's loop with 1 thread and with its default (every core).

    Alternated ``rounds`` times (1, default, 1, default ...), so both see the same load.
    """
    out: dict[str, list[float]] = {'wall_1': [], 'cpu_1': [], 'wall_all': [], 'cpu_all': []}
    for _ in range(rounds):
        for threads, key in ((1, '1'), (0, 'all')):
            wall, cpu = time.perf_counter(), time.process_time()
            kiss_pipeline(bag, topic, threads)
            out['wall_' + key].append(time.perf_counter() - wall)
            out['cpu_' + key].append(time.process_time() - cpu)
    return out


_LOOP_CPU = """
import sys, time
from skidkin_ros.adapters.bag_reader import open_recording
from skidkin_ros.adapters.lidar_gt import IcpConfig, register_frames
import kiss_icp.kiss_icp, scipy.spatial
with open_recording(sys.argv[1]) as rec:
    tic = time.process_time()
    register_frames(rec.iter_lidar('/points'), IcpConfig(voxel_size_m=float(sys.argv[2]),
                                                         convergence=float(sys.argv[3])))
    print(time.process_time() - tic)
"""


def loop_ab(bag: Path, config: Any, old: Path, rounds: int) -> dict[str, list[float]]:
    """CPU s of ``register_frames`` (reading included) over the bag, this code and ``old``'s.

    Each run is a fresh interpreter importing skidkin_ros from this checkout or from ``old``,
    alternated ``rounds`` times.
    """
    import os
    import subprocess

    here = str(Path(__file__).resolve().parents[2])
    out: dict[str, list[float]] = {'new': [], 'old': []}
    for _ in range(rounds):
        for key, root in (('old', str(old)), ('new', here)):
            done = subprocess.run(
                [sys.executable, '-c', _LOOP_CPU, str(bag), str(config.voxel_size_m),
                 str(config.convergence)], env=dict(os.environ, PYTHONPATH=root),
                capture_output=True, text=True, check=True)
            out[key].append(float(done.stdout.strip()))
    return out


def conversions_cost(bag: Path, topic: str) -> dict[str, float]:
    """CPU s of the numpy <-> C++ conversions kiss-icp's Python wrapper does, per call kind."""
    from kiss_icp.pybind import kiss_icp_pybind as kp

    from skidkin_ros.adapters.bag_reader import open_recording

    clouds = []
    with open_recording(str(bag)) as rec:
        for frame in rec.iter_lidar(topic):
            clouds.append(np.ascontiguousarray(np.asarray(frame.xyz, dtype=np.float64)))
    to_cpp = to_np = 0.0
    for cloud in clouds:
        # one at a time, as in the loop (600 clouds alive at once would time the page faults)
        tic = time.process_time()
        vector = kp._Vector3dVector(cloud)
        to_cpp += time.process_time() - tic
        tic = time.process_time()
        np.asarray(vector)
        to_np += time.process_time() - tic
    return {'frames': len(clouds), 'points_per_frame': float(np.mean([len(c) for c in clouds])),
            'numpy_to_cpp_s': to_cpp, 'cpp_to_numpy_s': to_np}


def accuracy(stamps: Sequence[int], poses: np.ndarray, sim: Any, extrinsic: np.ndarray
             ) -> tuple[float, float]:
    """Median 1 s increment error (cm, mrad) of a lidar track against the simulator."""
    from skidkin_ros.sim.accuracy import increment_errors

    track = gt_bench._track_of(poses, stamps, extrinsic)
    err = increment_errors(track, sim.pose_at, horizon_s=1.0, valid_only=False)
    return 100 * err.median_position_m, 1e3 * err.median_yaw_rad


def _parse_variant(text: str) -> tuple[str, dict[str, Any]]:
    label, _, body = text.partition('=')
    settings: dict[str, Any] = {}
    for item in body.split(','):
        key, _, value = item.partition('=')
        settings[key] = (value == 'true' if value in ('true', 'false')
                         else int(value) if value.isdigit() else float(value))
    return label, settings


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--scene', default='courtyard', choices=gt_scenes.SCENES)
    parser.add_argument('--duration', type=float, default=60.0)
    parser.add_argument('--seed', type=int, default=5)
    parser.add_argument('--kiss-threads', type=int, default=1)
    parser.add_argument('--threads-ab', type=int, default=0, metavar='R',
                        help="also time kiss-icp's loop with 1 thread and with every core, "
                        'alternated R times (wall and CPU)')
    parser.add_argument('--old', type=Path, metavar='DIR',
                        help='also time register_frames of the skidkin_ros in DIR against '
                        "this checkout's, alternated --rounds times (fresh interpreters)")
    parser.add_argument('--rounds', type=int, default=3)
    parser.add_argument('--variant', action='append', default=[], metavar='LABEL=K=V,...')
    parser.add_argument('--json', type=Path)
    args = parser.parse_args(argv)
    from skidkin_ros.adapters.icp_selfcheck import finer_than_reference, reference_config
    from skidkin_ros.adapters.lidar_gt import IcpConfig
    from skidkin_ros.adapters.sim_writer import write_bag
    from skidkin_ros.sim import simulate

    sim = simulate(gt_scenes.scene_config(args.scene, args.duration, args.seed))
    result: dict[str, Any] = {'scene': args.scene, 'seed': args.seed,
                              'duration_s': args.duration}
    with tempfile.TemporaryDirectory(prefix='gt_stages_') as tmp:
        bag, _ = write_bag(sim, Path(tmp) / 'bag')
        topic = '/points'
        from skidkin_ros.adapters.bag_reader import open_recording

        with open_recording(str(bag)) as rec:
            first = next(iter(rec.iter_lidar(topic)))
            extrinsic = rec.read_extrinsic('base_link', 'lidar')
        config = IcpConfig().with_voxel_for(first.xyz)
        reference = reference_config(config)
        if finer_than_reference(config, reference):
            config = reference
        result['settings'] = {'voxel_size_m': config.voxel_size_m,
                              'convergence': config.convergence}
        kiss_spent, n_frames = kiss_pipeline(bag, topic, args.kiss_threads)
        result['kiss'] = kiss_spent
        spent, stamps, poses = ours(bag, topic, config, new_loop=False)
        result['before'] = spent
        result['before_1s'] = accuracy(stamps, poses, sim, extrinsic)
        spent, stamps, poses = ours(bag, topic, config)
        result['ours'] = spent
        result['frames'] = n_frames
        result['conversions'] = conversions_cost(bag, topic)
        if args.old is not None:
            result['loop_ab'] = loop_ab(bag, config, args.old, args.rounds)
        if args.threads_ab:
            result['threads_ab'] = threads_ab(bag, topic, args.threads_ab)
        result['ours_1s'] = accuracy(stamps, poses, sim, extrinsic)
        for text in args.variant:
            label, settings = _parse_variant(text)
            spent, stamps, poses = ours(bag, topic, replace(config, **settings))
            result[label] = spent
            result[label + '_1s'] = accuracy(stamps, poses, sim, extrinsic)
    rows = ['kiss', 'before', 'ours'] + [_parse_variant(v)[0] for v in args.variant]
    print('| run | ' + ' | '.join(STAGES) + ' | total | 1 s cm / mrad |')
    print('|---' * (len(STAGES) + 3) + '|')
    for name in rows:
        spent = result[name]
        err = result.get(name + '_1s')
        print(f'| {name} | ' + ' | '.join(f'{spent[s]:.2f}' for s in STAGES)
              + f' | {sum(spent.values()):.2f} | '
              + (f'{err[0]:.2f} / {err[1]:.2f}' if err else '') + ' |')
    print(json.dumps(result, indent=1, default=float))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, default=float))
    return 0


if __name__ == '__main__':
    sys.exit(main())
