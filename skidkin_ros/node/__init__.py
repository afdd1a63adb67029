"""The ROS 2 layer: the live odometry node and an in-process replay harness (all rclpy code)."""
