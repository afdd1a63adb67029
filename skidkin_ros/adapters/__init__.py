"""Adapters that turn recordings (rosbag2 via rosbags) and lidar (kiss-icp) into core types."""
