"""skidkin_ros: calibrated skid-steer wheel odometry (ROS-free core, adapters, node, CLI)."""

__version__ = '0.1.0'

__all__ = ['__version__']
