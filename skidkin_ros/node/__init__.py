"""The ROS 2 layer: the live odometry node and an in-process replay harness (all rclpy code)."""

# The modules of this package (the API is theirs; ``skidkin_ros`` re-exports the public part).
__all__ = [
    'conversions',
    'diagnostics',
    'odom_node',
    'parameters',
    'replay',
    'wire',
]
