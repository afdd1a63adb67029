"""The bag reader's public names, kept where callers import them (see :mod:`.bags`)."""

from skidkin_ros.adapters.bags import (BagRecording, check_overlap, FLOAT64, format_summary, IMU,
                                       JOINT_STATE, keep_monotonic, LidarFrame, MAX_STAMP_JUMP_S,
                                       NoWheelInputError, ODOMETRY, open_recording, POINTCLOUD2,
                                       POSE_STAMPED, POSE_WITH_COVARIANCE, TF_MESSAGE,
                                       TopicSummary)

__all__ = [
    'JOINT_STATE',
    'FLOAT64',
    'POINTCLOUD2',
    'IMU',
    'ODOMETRY',
    'POSE_STAMPED',
    'POSE_WITH_COVARIANCE',
    'TF_MESSAGE',
    'TopicSummary',
    'LidarFrame',
    'BagRecording',
    'open_recording',
    'format_summary',
    'check_overlap',
    'keep_monotonic',
    'MAX_STAMP_JUMP_S',
    'NoWheelInputError',
]
