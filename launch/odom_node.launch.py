r"""Launch skidkin_ros's odom_node: a parameters file, use_sim_time, a namespace, topic remaps.

Examples::

    ros2 launch skidkin_ros odom_node.launch.py
    ros2 launch skidkin_ros odom_node.launch.py params_file:=/path/to/calibrated.yaml \
        use_sim_time:=true namespace:=husky joint_states_topic:=/husky/joint_states
    # A drive controller's odometry as the input (input: odometry in the parameters file):
    ros2 launch skidkin_ros odom_node.launch.py params_file:=odom_input.yaml \
        wheel_odom_topic:=/diff_drive_controller/odom odom_topic:=/wheel/odometry
    # Online calibration against kiss-icp's odometry (online.enabled: true in the file):
    ros2 launch skidkin_ros odom_node.launch.py params_file:=online.yaml \
        reference_topic:=/kiss/odometry

``params_file`` defaults to the installed example (share/skidkin_ros/config/odom_node.yaml);
a file written by ``skidkin calibrate`` loads the same way. Each ``*_topic`` argument remaps
one of the node's relative topic names (defaults: the names themselves, no remap).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

PACKAGE = 'skidkin_ros'
EXECUTABLE = 'odom_node'
DEFAULT_PARAMS = ('config', 'odom_node.yaml')
# Launch argument -> the node's own (relative) topic name it remaps.
REMAPS = {
    'joint_states_topic': 'joint_states',
    'left_wheel_topic': 'wheel/left/velocity',
    'right_wheel_topic': 'wheel/right/velocity',
    'wheel_odom_topic': 'wheel_odom',
    'imu_topic': 'imu/data',
    'reference_topic': 'reference/odom',
    'odom_topic': 'odom',
}


def generate_launch_description():
    """Declare the arguments and the node."""
    default_params = os.path.join(get_package_share_directory(PACKAGE), *DEFAULT_PARAMS)
    arguments = [
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS 2 parameters file (e.g. from skidkin calibrate)'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='use /clock (replaying a bag with --clock)'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the node and its relative topics'),
    ]
    arguments += [DeclareLaunchArgument(name, default_value=topic,
                                        description=f'topic the node uses as {topic}')
                  for name, topic in REMAPS.items()]
    node = Node(
        package=PACKAGE,
        executable=EXECUTABLE,
        name='odom_node',
        namespace=LaunchConfiguration('namespace'),
        output='screen',
        parameters=[LaunchConfiguration('params_file'),
                    {'use_sim_time': ParameterValue(LaunchConfiguration('use_sim_time'),
                                                    value_type=bool)}],
        remappings=[(topic, LaunchConfiguration(name)) for name, topic in REMAPS.items()],
    )
    return LaunchDescription(arguments + [node])
