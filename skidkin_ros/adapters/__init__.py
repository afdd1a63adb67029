"""Adapters that turn recordings (rosbag2 via rosbags) and lidar (kiss-icp) into core types."""

# The modules of this package (the API is theirs; ``skidkin_ros`` re-exports the public part).
__all__ = [
    'bag_reader',
    'bag_writer',
    'bags',
    'lidar_cache',
    'lidar_chunks',
    'lidar_gt',
    'lidar_guard',
    'lidar_plan',
    'lidar_pool',
    'lidar_seams',
    'pointcloud',
    'sim_writer',
    'sources',
    'table',
]
