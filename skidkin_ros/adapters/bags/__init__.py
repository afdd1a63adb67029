"""Read rosbag2 recordings (sqlite3 or mcap) into core types, streaming and defensively.

One module per job: ``open`` (storage files, damaged metadata, message types), ``stream``
(messages one at a time, drop counts), ``topics`` (listing, selection), ``wheels`` (JointState),
``floats`` (two Float64 topics), ``lidar``, ``imu``, ``poses`` (pose tracks, /tf_static chains),
joined in ``recording.BagRecording``; ``common`` holds the type names, defaults and helpers.

Entry point: ``open_recording(path) -> BagRecording`` (a context manager)::

    with open_recording('drive_bag') as bag:
        print(format_summary(bag.summary()))
        wheels = bag.read_wheels()                      # JointState, auto-detected
        for frame in bag.iter_lidar():                  # one LidarFrame at a time
            ...
        extrinsic = bag.read_extrinsic('base_link', 'os_lidar')   # 4x4 or None
        for line in bag.notes:                          # decisions the CLI should print
            print(line)

What it does with faulty recordings (fault rows of docs/fault-matrix.md):

- C1: a missing path is a RecordingError; a folder without metadata.yaml but with .db3 / .mcap
  files is read file by file (in order of their first message) and a note says so; so is a
  folder whose metadata.yaml cannot be read (the note names the error and ``ros2 bag reindex``).
  A path that is neither a file nor a folder (/dev/zero, a pipe) is a RecordingError.
- C2 / C3: a truncated mcap or a malformed sqlite3 file is a RecordingError naming the file and the
  remedy (``mcap recover`` / sqlite ``.recover``, then ``ros2 bag reindex``).
- C4: storage errors met while iterating (apsw, mcap parsing) and undecodable messages are skipped
  and counted; past ``max_corrupt`` skips in one pass, RecordingError. After a storage error the
  stream resumes just past the last good message, jumping ahead (1 ns, 2 ns, 4 ns ... of bag time)
  until the storage reads again, so a few neighbours of the corrupt message may be lost too.
- C5: every decoded value is validated (finite, bounded wheel speeds, non-zero stamps, stamps in
  order) and bad messages are dropped and counted; the counts go to ``notes``. Wheel samples
  whose speed jumps (faster than ``max_wheel_acceleration``: the node's rule, shared in
  :mod:`skidkin_ros.core.odometry.wheels`) are dropped too, and a note names the wheel side at
  fault: no fit and no check of the lidar ground truth against the wheels sees a spike. A topic
  the metadata lists but whose messages cannot be read says so.
  Stamps in order: the longest non-decreasing run of stamps is kept, so one corrupted stamp far
  in the future drops that message only, not everything after it; repeated stamps keep the first.
- C6: a message type neither in ROS 2 Jazzy nor defined in the bag is a RecordingError naming the
  topic and type, asking for the .msg file (``msg_files=`` of open_recording).
- C7: topics are picked by type when not named (exactly one candidate: used, and noted); none,
  several, a wrong type or an empty topic are RecordingErrors listing the topics and types there.
- C8: :func:`check_overlap` refuses two time ranges that barely overlap.
- C19: messages are read one at a time from the storage; nothing holds the whole bag.

Times are integer nanoseconds. ``header.stamp`` is used for the data (wheel speeds, clouds, poses,
imu); the bag receive time only for std_msgs/Float64 wheel topics, which have no header.
"""

from skidkin_ros.adapters.bags.common import (check_overlap, FLOAT64, format_summary, IMU,
                                              JOINT_STATE, keep_monotonic, MAX_STAMP_JUMP_S,
                                              NoWheelInputError, ODOMETRY, POINTCLOUD2,
                                              POSE_STAMPED, POSE_WITH_COVARIANCE, TF_MESSAGE,
                                              TopicSummary)
from skidkin_ros.adapters.bags.lidar import LidarFrame
from skidkin_ros.adapters.bags.recording import BagRecording, open_recording

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
