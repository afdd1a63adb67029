"""A rosbags bag of a drive's wheels and a reference, for the online-calibration tests.

JointState on ``/joint_states`` (two wheels a side) and nav_msgs/Odometry on ``topic``, each
reference pose written before the first wheel sample stamped at or after it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

from skidkin_ros.adapters.bag_writer import BagWriter
from skidkin_ros.core.drive import PoseTrack, WheelSamples
from skidkin_ros.sim.simulate import JOINT_NAMES


def write_reference_bag(path: Path, wheels: WheelSamples, topic: str, track: PoseTrack,
                        frame_id: str, child_frame_id: str,
                        covariance: Callable[[int], Sequence[float]] | None = None) -> Path:
    """Write the bag; ``covariance(j)``: the 36 pose-covariance values of reference pose j."""
    with BagWriter(path) as writer:
        j = 0
        for i, t in enumerate(wheels.t_ns.tolist()):
            while j < len(track) and track.t_ns[j] <= t:
                more = {} if covariance is None else {'pose_covariance': covariance(j)}
                writer.write_odometry(topic, int(track.t_ns[j]), frame_id, child_frame_id,
                                      track.x[j], track.y[j], track.yaw[j], **more)
                j += 1
            writer.write_joint_state('/joint_states', t, JOINT_NAMES,
                                     [wheels.omega_l[i]] * 2 + [wheels.omega_r[i]] * 2)
    return path
