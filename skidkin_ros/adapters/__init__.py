"""Adapters that turn recordings (rosbag2 via rosbags) and lidar (kiss-icp) into core types."""

# The modules of this package (the API is theirs; ``skidkin_ros`` re-exports the public part).
__all__ = [
    'bag_reader',
    'bag_writer',
    'bags',
    'icp_config',
    'lidar_cache',
    'lidar_chunks',
    'lidar_frames',
    'lidar_gt',
    'lidar_guard',
    'lidar_plan',
    'lidar_pool',
    'lidar_quality',
    'lidar_register',
    'lidar_seams',
    'pointcloud',
    'sim_writer',
    'sources',
    'table',
]
