"""The ROS-free core: models, SE(2) integration, calibration, evaluation. Never imports rclpy."""

# The modules of this package (the API is theirs; ``skidkin_ros`` re-exports the public part).
__all__ = [
    'calibration',
    'drive',
    'estimation',
    'kinematics',
    'odometry',
    'online',
    'parallel',
    'rigid',
    'rotation',
    'timeunits',
]
