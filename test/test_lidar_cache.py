"""Lidar input faults: a cache folder that cannot be written, clouds without x, y, z.

Neither loses the ground truth or blames the recording. Real kiss-icp on a short bag written by
rosbags (chunks of 5 s).
"""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
from skidkin_ros.adapters.bag_reader import open_recording
from skidkin_ros.adapters.lidar_chunks import bag_ground_truth, ChunkOptions
from skidkin_ros.adapters.lidar_gt import IcpConfig
from skidkin_ros.adapters.sim_writer import write_bag
from skidkin_ros.sim import LidarConfig, SimConfig, simulate

LIDAR = LidarConfig(azimuth_resolution_deg=2.0, mount_xyz_m=(0.3, 0.1, 0.5), mount_yaw_rad=0.4)
ICP = IcpConfig(voxel_size_m=0.5, max_range_m=50.0)
CHUNKS = ChunkOptions(chunk_s=5.0, overlap_s=2.0)


def test_an_unwritable_cache_folder_warns_once_and_keeps_every_chunk(tmp_path, caplog):
    sim = simulate(SimConfig(duration_s=11.0, seed=4, lidar=LIDAR, internal_rate_hz=200.0))
    bag, _ = write_bag(sim, tmp_path / 'drive')
    # /proc takes no new file, root included (a read-only folder does not stop root)
    unwritable = Path('/proc')
    with caplog.at_level(logging.WARNING), open_recording(bag) as rec:
        truth = bag_ground_truth(rec, bag, '/points', LIDAR.extrinsic(), ICP, CHUNKS,
                                 cache_dir=unwritable)
    with open_recording(bag) as rec:
        plain = bag_ground_truth(rec, bag, '/points', LIDAR.extrinsic(), ICP, CHUNKS)
    assert (truth.track.poses == plain.track.poses).all() and truth.track.valid.all()
    assert not any('failed' in note for note in truth.notes)
    said = [r.getMessage() for r in caplog.records if 'cannot be written' in r.getMessage()]
    assert len(said) == 1 and 'computed and written as usual, but not cached' in said[0]


def test_clouds_without_x_y_z_are_named_as_the_cause_not_a_damaged_recording(tmp_path):
    import numpy as np
    from skidkin_ros.adapters.bag_writer import BagWriter
    from skidkin_ros.adapters.pointcloud import pack_points
    from skidkin_ros.errors import RecordingError
    with BagWriter(tmp_path / 'bag') as writer:
        for k in range(40):
            points = np.random.default_rng(k).normal(size=(50, 3))
            specs, step, data = pack_points([(name, points[:, i], np.float32)
                                             for i, name in enumerate(('a', 'b', 'c'))])
            field = writer._types['sensor_msgs/msg/PointField']
            msg = writer._types['sensor_msgs/msg/PointCloud2'](
                header=writer._header(10**18 + k * 10**8, None, 'lidar'), height=1, width=50,
                fields=[field(name=s.name, offset=s.offset, datatype=s.datatype, count=s.count)
                        for s in specs], is_bigendian=False, point_step=step,
                row_step=step * 50, data=data, is_dense=True)
            writer.write_message('/points', 10**18 + k * 10**8, msg)
    with open_recording(tmp_path / 'bag') as rec:
        with pytest.raises(RecordingError) as err:
            list(rec.iter_lidar('/points'))
    text = str(err.value)
    assert "no field(s) ['x', 'y', 'z']" in text and 'The recording reads fine' in text
    assert 'recover' not in text and 'damaged' not in text


@pytest.mark.heavy
def test_ctrl_c_with_two_jobs_stops_the_workers_instead_of_waiting_for_their_chunks(tmp_path):
    # A bound on a hang, not a speed target: the workers ignore Ctrl-C (left to the parent),
    # which waited for their chunks (7 s with 5 s chunks, about 15 s with these 10 s ones).
    # The signal goes once the pool's workers are up (their chunks take seconds each): 180 s in
    # 18 chunks keeps the run going well past that on a fast machine (60 s took 5.7 s in all).
    import os
    import signal
    import subprocess
    import sys
    import time
    import psutil
    sim = simulate(SimConfig(duration_s=180.0, seed=8, lidar=LidarConfig(
        azimuth_resolution_deg=1.0, mount_xyz_m=(0.3, 0.1, 0.5), mount_yaw_rad=0.4),
        internal_rate_hz=200.0))
    bag, _ = write_bag(sim, tmp_path / 'drive')
    command = [sys.executable, '-m', 'skidkin_ros.cli.main', 'groundtruth', str(bag), '--out',
               str(tmp_path / 'gt.csv'), '--jobs', '2', '--no-cache', '--chunk-s', '10',
               '--chunk-overlap', '2', '--no-progress']
    run = subprocess.Popen(command, stderr=subprocess.PIPE, text=True, env=dict(os.environ))
    parent, deadline = psutil.Process(run.pid), time.monotonic() + 60.0
    # the forkserver and the two workers under it: the chunks are being registered
    while len(parent.children(recursive=True)) < 3 and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)
    assert run.poll() is None
    interrupted = time.monotonic()
    run.send_signal(signal.SIGINT)
    _, err = run.communicate(timeout=60)
    assert run.returncode == 130 and 'interrupted' in err and 'Traceback' not in err
    assert time.monotonic() - interrupted < 5.0
    assert not (tmp_path / 'gt.csv').exists()
