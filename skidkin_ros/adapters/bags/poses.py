"""Pose tracks (ground truth topics) and the extrinsic from /tf_static chains."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from skidkin_ros.adapters.bags.common import (ODOMETRY, POSE_STAMPED, POSE_WITH_COVARIANCE,
                                              stamp_ns, TF_MESSAGE)
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.core.rotation import quaternion_to_yaw
from skidkin_ros.errors import RecordingError


class PosesMixin:
    """read_pose_track and read_extrinsic."""

    # -- poses -----------------------------------------------------------------------------------
    def read_pose_track(self, topic: str | None = None) -> PoseTrack:
        """Return a planar track (x, y m; unwrapped yaw rad) from a pose topic.

        nav_msgs/Odometry, geometry_msgs/PoseStamped or geometry_msgs/PoseWithCovarianceStamped
        (AMCL's amcl_pose, robot_localization's map pose); of the covariance only the yaw
        variance is kept (``yaw_variance``; NaN for PoseStamped): online calibration reads it.
        """
        chosen = self.select((ODOMETRY, POSE_STAMPED, POSE_WITH_COVARIANCE), topic,
                             'ground truth')
        rows: list[tuple[int, float, float, float]] = []
        variances: list[float] = []
        for _, msg in self.messages(chosen):
            # Odometry and PoseWithCovarianceStamped hold a PoseWithCovariance; PoseStamped a Pose.
            covariance = getattr(msg.pose, 'covariance', None)
            pose = msg.pose.pose if covariance is not None else msg.pose
            q = pose.orientation
            yaw = quaternion_to_yaw(q.x, q.y, q.z, q.w)
            row = (stamp_ns(msg.header), float(pose.position.x), float(pose.position.y), yaw)
            if not all(math.isfinite(v) for v in row[1:]):
                self._drop(chosen, 'non-finite pose')
                continue
            rows.append(row)
            variances.append(math.nan if covariance is None else float(covariance[35]))
        if not rows:
            raise RecordingError(f'ground truth: no valid pose on {chosen} '
                                 f'({self._reasons(chosen)})')
        t = np.array([r[0] for r in rows], dtype=np.int64)
        xyyaw = np.array([r[1:] for r in rows], dtype=np.float64)
        keep = self._keep_in_order(chosen, t)
        xyyaw = xyyaw[keep]
        return PoseTrack(t[keep], xyyaw[:, 0], xyyaw[:, 1], np.unwrap(xyyaw[:, 2]),
                         yaw_variance=np.array(variances, dtype=np.float64)[keep])

    def read_pose_frames(self, topic: str) -> list[tuple[int, str, str]]:
        """Return (stamp ns, header.frame_id, child_frame_id) of every pose on ``topic``.

        PoseStamped and PoseWithCovarianceStamped have no child frame: ''.
        """
        return [(stamp_ns(msg.header), str(msg.header.frame_id),
                 str(getattr(msg, 'child_frame_id', ''))) for _, msg in self.messages(topic)]

    # -- extrinsic -------------------------------------------------------------------------------
    def read_extrinsic(self, base_frame: str, lidar_frame: str, topic: str = '/tf_static'
                       ) -> np.ndarray | None:
        """Return the 4x4 pose of ``lidar_frame`` in ``base_frame`` from /tf_static, or None.

        Chains through intermediate frames in either direction. None (with a note) when the topic
        is absent or no chain joins the two frames.
        """
        base, lidar = base_frame.lstrip('/'), lidar_frame.lstrip('/')
        if topic not in self.topics():
            self.notes.append(f'extrinsic: no {topic} in the recording; give the '
                              f'{base}->{lidar} transform in the configuration')
            return None
        self.select(TF_MESSAGE, topic, 'extrinsic')
        edges: dict[str, dict[str, np.ndarray]] = {}
        for _, msg in self.messages(topic):
            for tf in msg.transforms:
                parent, child = tf.header.frame_id.lstrip('/'), tf.child_frame_id.lstrip('/')
                matrix = _transform_matrix(tf.transform)
                if matrix is None:
                    self._drop(topic, 'non-finite transform')
                    continue
                edges.setdefault(parent, {})[child] = matrix
                edges.setdefault(child, {})[parent] = np.linalg.inv(matrix)
        if base == lidar:
            return np.eye(4)
        chain = _find_chain(edges, base, lidar)
        if chain is None:
            self.notes.append(f'extrinsic: {topic} does not join {base} and {lidar} (frames: '
                              f'{sorted(edges)}); give the transform in the configuration')
            return None
        self.notes.append(f'extrinsic: {base} -> {lidar} from {topic} via {" -> ".join(chain)}')
        result = np.eye(4)
        for a, b in zip(chain[:-1], chain[1:]):
            result = result @ edges[a][b]
        return result


def _transform_matrix(transform: Any) -> np.ndarray | None:
    """Return a geometry_msgs/Transform as a 4x4 matrix; None when not finite or no rotation."""
    t, q = transform.translation, transform.rotation
    quaternion = [float(q.x), float(q.y), float(q.z), float(q.w)]  # scipy's order: x, y, z, w
    translation = [float(t.x), float(t.y), float(t.z)]
    if (not all(math.isfinite(v) for v in translation + quaternion)
            or math.hypot(*quaternion) < 1e-9):
        return None
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_quat(quaternion).as_matrix()  # normalizes the quaternion
    matrix[:3, 3] = translation
    return matrix


def _find_chain(edges: dict[str, dict[str, np.ndarray]], start: str, goal: str
                ) -> list[str] | None:
    previous: dict[str, str | None] = {start: None}
    queue = [start]
    while queue:
        frame = queue.pop(0)
        if frame == goal:
            chain = [goal]
            while previous[chain[-1]] is not None:
                chain.append(previous[chain[-1]])
            return chain[::-1]
        for neighbour in edges.get(frame, {}):
            if neighbour not in previous:
                previous[neighbour] = frame
                queue.append(neighbour)
    return None
