"""Ground truth at the speed of the lidar: the outdoor scene, against the plain kiss_icp_pipeline.

What it measures, on simulated outdoor drives (an open field with 400 trees, a flat ground, a
VLP-16-like lidar: 16 rings, 360 columns, 10 Hz, per-point times, base -> lidar on /tf_static):

* **side by side**: ``kiss_icp_pipeline --topic /points BAG`` (kiss-icp's own tool, reading the
  ROS 2 bag through rosbags, its default settings, every core) and ``skidkin groundtruth BAG
  --no-cache`` (chunks on every core) on the same recording, as subprocesses, in the order
  kiss, skidkin, skidkin, kiss, so both see the machine in the same states. Ratio = total kiss
  wall time / total skidkin wall time; real-time factor = recording duration / wall time.
  Accuracy of both against the simulator's truth over 1 s and 2 m increments.
* **why** the ground truth was slower than kiss-icp's tool: each difference measured alone on
  the same frames in memory, kiss-icp with one thread (CPU ms per frame: the process's CPU
  time, which the machine's load disturbs less than wall time), and the per-frame overheads
  (bag reading by skidkin's reader and by kiss-icp's, the guard).
* **a 10-minute drive from bag to parameters file**: ``skidkin calibrate BAG`` wall time.

Run as part of ``python lab/bench/run.py`` (part ``groundtruth``).
"""

from __future__ import annotations

import os
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile
import time
from typing import Any, Sequence

import numpy as np
from skidkin_ros.core.parallel import usable_cpus


def vlp16() -> Any:
    """Return the VLP-16-like lidar of the outdoor benchmark."""
    from skidkin_ros.sim import LidarConfig

    return LidarConfig(n_rings=16, azimuth_resolution_deg=1.0, rate_hz=10.0, range_noise_m=0.02,
                       max_range_m=100.0, mount_xyz_m=(0.2, 0.0, 0.7))


def outdoor_config(duration_s: float, seed: int) -> Any:
    """Return the SimConfig of an outdoor drive (forest scene, VLP-16-like lidar)."""
    from skidkin_ros.sim import SimConfig

    return SimConfig(duration_s=duration_s, seed=seed, lidar=vlp16(), scene='forest',
                     scene_half_size_m=16.0, arena_radius_m=8.0, internal_rate_hz=200.0)


def write_outdoor(folder: Path, duration_s: float, seed: int) -> tuple[Path, Any]:
    """Simulate an outdoor drive and write it as a bag; return (bag, simulation)."""
    from skidkin_ros.adapters.sim_writer import write_bag
    from skidkin_ros.sim import simulate

    sim = simulate(outdoor_config(duration_s, seed))
    bag, _ = write_bag(sim, folder / f'outdoor_{int(duration_s)}s_seed{seed}')
    return bag, sim


def _errors(track: Any, sim: Any) -> dict[str, float]:
    from skidkin_ros.sim.accuracy import increment_errors

    one = increment_errors(track, sim.pose_at, horizon_s=1.0, valid_only=False)
    two = increment_errors(track, sim.pose_at, horizon_m=2.0, valid_only=False)
    return {'pos_1s_m': one.median_position_m, 'yaw_1s_rad': one.median_yaw_rad,
            'pos_2m_m': two.median_position_m, 'yaw_2m_rad': two.median_yaw_rad}


def _timed(command: Sequence[str], env: dict[str, str] | None = None,
           cwd: Path | None = None) -> tuple[float, int, str]:
    tic = time.perf_counter()
    proc = subprocess.run(list(command), env=env, cwd=cwd, stdout=subprocess.DEVNULL,
                          stderr=subprocess.PIPE, text=True, timeout=7200)
    return time.perf_counter() - tic, proc.returncode, (proc.stderr or '')[-2000:]


def _kiss_command() -> list[str]:
    return [str(Path(sys.executable).with_name('kiss_icp_pipeline'))]


def _skidkin_command() -> list[str]:
    return [str(Path(sys.executable).with_name('skidkin'))]


def kiss_track(results_dir: Path, bag: Path) -> Any:
    """Return kiss_icp_pipeline's poses as a base_link PoseTrack stamped like our frames."""
    from skidkin_ros.adapters.bag_reader import open_recording

    poses = np.load(next(results_dir.rglob('*_poses.npy')))
    with open_recording(bag) as rec:
        ends = [f.end_ns for f in rec.iter_lidar('/points')]
        extrinsic = rec.read_extrinsic('base_link', 'lidar')
    n = min(len(ends), poses.shape[0])
    return _track_of(poses[:n], ends[:n], extrinsic)


def side_by_side(bag: Path, sim: Any, jobs: int, rounds: int = 2) -> dict[str, Any]:
    """Time kiss_icp_pipeline and skidkin groundtruth on one bag, ABBA-interleaved."""
    from skidkin_ros.core.drive import PoseTrack

    duration_s = (sim.end_ns - sim.start_ns) * 1e-9
    kiss_s: list[float] = []
    ours_s: list[float] = []
    errors: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix='gt_bench_') as tmp:
        work = Path(tmp)
        env = dict(os.environ, kiss_icp_out_dir=str(work / 'kiss'))
        order = ['kiss', 'skidkin', 'skidkin', 'kiss'] * max(1, rounds // 2)
        for i, who in enumerate(order):
            if who == 'kiss':
                seconds, code, err = _timed(_kiss_command() + ['--topic', '/points', str(bag)],
                                            env=env, cwd=work)
                kiss_s.append(seconds)
            else:
                out = work / f'traj_{i}.csv'
                seconds, code, err = _timed(
                    _skidkin_command() + ['groundtruth', str(bag), '--out', str(out), '--force',
                                          '--no-cache', '--jobs', str(jobs)])
                ours_s.append(seconds)
            if code != 0:
                return {'error': f'{who} exited {code}: {err}'}
        ours = np.genfromtxt(work / 'traj_1.csv', delimiter=',', names=True)
        track = PoseTrack(ours['t_ns'].astype(np.int64), ours['x'], ours['y'], ours['yaw'],
                          ours['valid'].astype(bool))
        errors['skidkin'] = _errors(track, sim)
        errors['skidkin']['valid_share'] = float(track.valid.mean())
        errors['kiss'] = _errors(kiss_track(work / 'kiss', bag), sim)
    return {'duration_s': duration_s, 'frames': int(len(track)), 'kiss_s': kiss_s,
            'skidkin_s': ours_s, 'jobs': jobs, 'speedup': sum(kiss_s) / sum(ours_s),
            'kiss_rtf': duration_s * len(kiss_s) / sum(kiss_s),
            'skidkin_rtf': duration_s * len(ours_s) / sum(ours_s), 'errors': errors}


# -- why: each difference alone, on the same frames in memory -----------------------------------
def _plain_kiss(frames: Sequence[Any], config: Any) -> np.ndarray:
    from kiss_icp.kiss_icp import KissICP

    odometry = KissICP(config)
    poses = []
    for frame in frames:
        odometry.register_frame(frame.xyz, frame.t_rel_s if config.data.deskew else np.zeros(0))
        poses.append(odometry.last_pose.copy())
    return np.array(poses)


def _kiss_config(max_range: float, voxel: float, deskew: bool = True,
                 convergence: float = 1e-4) -> Any:
    """Return kiss-icp's config of one variant (kiss-icp's defaults otherwise, one thread)."""
    from skidkin_ros.adapters.lidar_gt import IcpConfig

    return IcpConfig(max_range_m=max_range, min_range_m=0.5 if max_range == 60.0 else 0.0,
                     voxel_size_m=voxel, deskew=deskew, convergence=convergence,
                     max_threads=1).kiss_config()


def _track_of(poses: np.ndarray, ends_ns: Sequence[int], extrinsic: np.ndarray) -> Any:
    """Return lidar poses (N, 4, 4) as a base_link PoseTrack stamped with the frames' ends."""
    from skidkin_ros.core.drive import PoseTrack
    from skidkin_ros.core.rigid import planar_poses

    rows = planar_poses(poses, extrinsic)
    return PoseTrack(np.array(ends_ns, dtype=np.int64), rows[:, 0], rows[:, 1],
                     np.unwrap(rows[:, 2]))


def why(bag: Path, sim: Any, n_frames: int) -> dict[str, Any]:
    """Measure each difference between skidkin's ground truth and kiss-icp's tool alone."""
    from skidkin_ros.adapters.bag_reader import open_recording
    from skidkin_ros.adapters.lidar_gt import guarded_truth, IcpConfig, register_frames

    rows: list[dict[str, Any]] = []
    with open_recording(bag) as rec:
        tic = time.process_time()
        frames = [f for _, f in zip(range(n_frames), rec.iter_lidar('/points'))]
        read_ours = (time.process_time() - tic) / len(frames)
        extrinsic = rec.read_extrinsic('base_link', 'lidar')
    rows.append({'what': 'bag reading, skidkin (BagRecording.iter_lidar)',
                 'cpu_ms': 1e3 * read_ours})
    rows.append({'what': "bag reading, kiss-icp's rosbag loader",
                 'cpu_ms': 1e3 * _kiss_reading(bag, n_frames)})
    variants = [
        ('kiss-icp defaults (range 100 m, voxel 1.0 m): kiss_icp_pipeline', (100.0, 1.0)),
        ('skidkin before: range 60 m, so voxel 0.6 m (max_range / 100)', (60.0, 0.6)),
        ('skidkin before, deskew off', (60.0, 0.6, False)),
        ('skidkin before, voxel 1.0 m', (60.0, 1.0)),
        ('skidkin before, convergence 1e-3', (60.0, 0.6, True, 1e-3)),
    ]
    for label, args in variants:
        config = _kiss_config(*args)
        tic = time.process_time()
        poses = _plain_kiss(frames, config)
        cpu = (time.process_time() - tic) / len(frames)
        row = {'what': label, 'cpu_ms': 1e3 * cpu}
        row.update(_errors(_track_of(poses, [f.end_ns for f in frames], extrinsic), sim))
        rows.append(row)
    for label, config in (('skidkin now (auto voxel, range 100 m, convergence 1e-3, quality '
                           'measured)', IcpConfig()),
                          ('skidkin now, without the quality measurement',
                           IcpConfig(quality_points=0))):
        tic = time.process_time()
        registration = register_frames(frames, config)
        cpu = (time.process_time() - tic) / len(frames)
        tic = time.process_time()
        truth = guarded_truth(registration, extrinsic, config, wheels=sim.wheels, imu=sim.imu)
        guard = (time.process_time() - tic) / len(frames)
        row = {'what': label, 'cpu_ms': 1e3 * cpu, 'voxel_m': registration.voxel_size_m}
        row.update(_errors(truth.track, sim))
        rows.append(row)
    rows.append({'what': 'guard (flags from ICP quality, IMU, wheels)', 'cpu_ms': 1e3 * guard})
    return {'frames': len(frames), 'rows': rows}


def _kiss_reading(bag: Path, n_frames: int) -> float:
    from kiss_icp.datasets.rosbag import RosbagDataset

    dataset = RosbagDataset(bag, '/points')
    count = min(n_frames, len(dataset))
    tic = time.process_time()
    for index in range(count):
        dataset[index]
    return (time.process_time() - tic) / max(count, 1)


def calibrate_drive(bag: Path, duration_s: float, jobs: int) -> dict[str, Any]:
    """Time ``skidkin calibrate`` from the bag to the parameters file (no cache)."""
    with tempfile.TemporaryDirectory(prefix='gt_calib_') as tmp:
        out = Path(tmp) / 'params.yaml'
        seconds, code, err = _timed(_skidkin_command() + [
            'calibrate', str(bag), '--out', str(out), '--no-cache', '--jobs', str(jobs),
            '--no-progress'])
        written = out.is_file()
    return {'duration_s': duration_s, 'seconds': seconds, 'exit_code': code,
            'written': written, 'error': None if code in (0, 4) else err}


def run(folder: Path, outdoor_s: float, drive_s: float, why_frames: int,
        jobs: int) -> dict[str, Any]:
    """Run the whole ground-truth benchmark; return its rows."""
    bag, sim = write_outdoor(folder, outdoor_s, seed=16)
    result: dict[str, Any] = {'outdoor_s': outdoor_s, 'jobs': jobs}
    result['points_per_frame'] = float(np.mean(
        [len(scan) for _, scan in zip(range(20), sim.scans())]))
    print('  groundtruth: side by side with kiss_icp_pipeline', flush=True)
    result['side_by_side'] = side_by_side(bag, sim, jobs)
    print('  groundtruth: why', flush=True)
    result['why'] = why(bag, sim, why_frames)
    shutil.rmtree(bag, ignore_errors=True)
    print(f'  groundtruth: a {drive_s:g} s drive from bag to parameters', flush=True)
    drive_bag, _ = write_outdoor(folder, drive_s, seed=17)
    result['calibrate'] = calibrate_drive(drive_bag, drive_s, jobs)
    return result


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ground-truth benchmark alone and print its JSON."""
    import argparse
    import json

    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--outdoor-s', type=float, default=300.0)
    parser.add_argument('--drive-s', type=float, default=600.0)
    parser.add_argument('--why-frames', type=int, default=300)
    parser.add_argument('--jobs', type=int, default=usable_cpus())
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix='gt_bench_') as tmp:
        result = run(Path(tmp), args.outdoor_s, args.drive_s, args.why_frames, args.jobs)
    print(json.dumps(result, indent=1, default=str))
    return 0


if __name__ == '__main__':
    sys.exit(main())
