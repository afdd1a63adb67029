"""The node's requests: ``~/reset``, ``~/set_pose`` and ``~/save_calibration``.

Reset and set_pose change the pose and its covariance only; the integration baseline stays
(fault row N81). Saving writes the learned parameters atomically, never over an existing file.
"""

from __future__ import annotations

from typing import Any, Sequence

from geometry_msgs.msg import PoseWithCovarianceStamped
import numpy as np
from skidkin_ros.core.online.save import save_learned
from skidkin_ros.errors import SkidkinError
from skidkin_ros.node.callbacks import guarded as _guarded
from skidkin_ros.node.conversions import planar_covariance_from_msg, planar_pose_from_msg
from std_srvs.srv import Trigger

__all__ = ['PoseRequests']


class PoseRequests:
    """The request half of :class:`~skidkin_ros.node.odom_node.OdomNode` (a mixin of it)."""

    @_guarded
    def _on_save_calibration(self, request: Trigger.Request,
                             response: Trigger.Response) -> Any:
        """Write the learned parameters as a parameters file the node loads as is."""
        with self._lock:
            learner = self._odometer.learner
            if learner is None:
                response.success = False
                response.message = ('online.enabled is false: nothing learned to save (the '
                                    "parameters in force are the file's)")
                return response
            try:
                path = save_learned(self._config, learner, self._config['online.save_path'],
                                    {'node': self.get_fully_qualified_name(),
                                     'reference_topic': self._reference_sub.topic_name})
            except SkidkinError as err:
                response.success = False
                response.message = f'not saved: {err}'
                self.counters['save_refused'] += 1
                return response
            self.counters['saved'] += 1
        self.get_logger().info(f'learned calibration saved to {path}')
        response.success = True
        response.message = f'saved to {path}'
        return response

    @_guarded
    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        with self._lock:
            self._reset_state((0.0, 0.0, 0.0))
            self.counters['reset'] += 1
        self.get_logger().info('odometry reset to the origin')
        response.success = True
        response.message = 'pose and covariance reset to zero'
        return response

    @_guarded
    def _on_set_pose(self, msg: PoseWithCovarianceStamped) -> None:
        with self._lock:
            try:
                pose = planar_pose_from_msg(msg.pose.pose)
                # Checks the pose and covariance (bounded, finite) before changing anything.
                self._reset_state(pose, planar_covariance_from_msg(msg.pose.covariance))
            except ValueError as err:
                self._reject('set_pose_rejected', f'set_pose rejected, the pose is kept: {err}')
                return
            self.counters['set_pose'] += 1
        self.get_logger().info(f'pose set to x {pose[0]:.3f} m, y {pose[1]:.3f} m, '
                               f'yaw {pose[2]:.3f} rad')

    def _reset_state(self, pose: Sequence[float], covariance: np.ndarray | None = None) -> None:
        self._odometer.reset(pose, covariance)
