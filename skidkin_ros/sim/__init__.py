"""The project's own simulator: a skid-steer robot, named effects and a ray-cast lidar.

numpy/scipy only (no ROS, no I/O): it produces data. A simulation is written as a rosbag2 (and
its truth as a trajectory table) by :mod:`skidkin_ros.adapters.sim_writer`.
"""

from skidkin_ros.sim.effects import Effect, EFFECT_NAMES, EFFECTS, make_effect, random_effect
from skidkin_ros.sim.lidar import LidarConfig, LidarScan
from skidkin_ros.sim.simulate import SimConfig, simulate, Simulation

__all__ = ['EFFECT_NAMES', 'EFFECTS', 'Effect', 'LidarConfig', 'LidarScan', 'SimConfig',
           'Simulation', 'make_effect', 'random_effect', 'simulate']
