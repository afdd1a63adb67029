"""The project's own simulator: a skid-steer robot, named effects and a ray-cast lidar.

numpy/scipy only (no ROS); bags are written through skidkin_ros.adapters.bag_writer.
"""

from skidkin_ros.sim.effects import Effect, EFFECT_NAMES, EFFECTS, make_effect, random_effect
from skidkin_ros.sim.lidar import LidarConfig, LidarScan
from skidkin_ros.sim.simulate import SimConfig, simulate, Simulation, write_bag, write_truth_csv

__all__ = ['EFFECT_NAMES', 'EFFECTS', 'Effect', 'LidarConfig', 'LidarScan', 'SimConfig',
           'Simulation', 'make_effect', 'random_effect', 'simulate', 'write_bag',
           'write_truth_csv']
