"""The ROS-free core: models, SE(2) integration, calibration, evaluation. Never imports rclpy."""
