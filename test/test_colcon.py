"""colcon build of the package and the installed odom_node executable, end to end."""

import os
from pathlib import Path
import shutil
import subprocess
import sys
import time

from nav_msgs.msg import Odometry
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from skidkin_ros.core.odometry.config import write_params_file
from skidkin_ros.node.conversions import ns_to_stamp

pytestmark = [pytest.mark.heavy, pytest.mark.ros]

SOURCE = Path(__file__).resolve().parents[1]
COLCON = Path(sys.executable).with_name('colcon')
SKIP = shutil.ignore_patterns('.venv', 'build', 'install', 'log', '.git', '.pytest_cache',
                              '__pycache__', '*.egg-info', 'demo_out', 'out', 'results')
NS_PER_S = 1_000_000_000


@pytest.fixture(scope='module')
def installed(tmp_path_factory):
    """Build the package with colcon in a temporary workspace; return (workspace, env)."""
    workspace = tmp_path_factory.mktemp('ws')
    shutil.copytree(SOURCE, workspace / 'src' / 'skidkin_ros', ignore=SKIP)
    done = subprocess.run([str(COLCON), 'build', '--base-paths', 'src'], cwd=workspace,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    site = next((workspace / 'install' / 'skidkin_ros' / 'lib').glob('python*/site-packages'))
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join([str(site), env.get('PYTHONPATH', '')])
    env['PYTHONUNBUFFERED'] = '1'
    return workspace, env


def executable(workspace):
    return workspace / 'install' / 'skidkin_ros' / 'lib' / 'skidkin_ros' / 'odom_node'


def test_installed_layout(installed):
    workspace, env = installed
    share = workspace / 'install' / 'skidkin_ros' / 'share' / 'skidkin_ros'
    assert executable(workspace).is_file()
    assert (share / 'config' / 'odom_node.yaml').is_file()
    assert (share / 'launch' / 'odom_node.launch.py').is_file()
    assert (share / 'package.xml').is_file()
    where = subprocess.run([sys.executable, '-c', 'import skidkin_ros.node.odom_node as m; '
                            'print(m.__file__)'], env=env, capture_output=True, text=True,
                           cwd=workspace)
    assert str(workspace / 'install') in where.stdout, where.stderr  # the built copy runs
    # The lab (studies, benchmarks) stays in the source tree: nothing of it is installed.
    site = next((workspace / 'install' / 'skidkin_ros' / 'lib').glob('python*/site-packages'))
    assert (site / 'skidkin_ros').is_dir() and not (site / 'lab').exists()
    assert not list(site.glob('skidkin_ros/**/studies')) and not (site / 'bench').exists()


def test_missing_params_file_exit_code(installed, tmp_path):
    workspace, env = installed
    missing = tmp_path / 'absent.yaml'
    done = subprocess.run([str(executable(workspace)), '--ros-args', '--params-file',
                           str(missing)], env=env, capture_output=True, text=True, timeout=30,
                          cwd=workspace)
    assert done.returncode == 2
    assert str(missing) in done.stderr and 'Traceback' not in done.stderr


def test_invalid_parameter_exit_code(installed):
    workspace, env = installed
    done = subprocess.run([str(executable(workspace)), '--ros-args', '-p', 'max_dt:=-1.0'],
                          env=env, capture_output=True, text=True, timeout=30, cwd=workspace)
    assert done.returncode == 2
    assert "'max_dt'" in done.stderr and 'Traceback' not in done.stderr


def test_installed_node_publishes_odometry(installed, tmp_path):
    workspace, env = installed
    namespace = f'colcon{os.getpid()}'
    params = write_params_file(tmp_path / 'robot.yaml', {
        'wheel_radius': 0.2, 'track_width': 0.5, 'model': 'ideal_dd',
        'models.edd_symmetric.alpha': 0.8, 'base_frame_id': 'chassis'})
    # The file configures everything; -p switches the model (alpha 0.8 must show below).
    process = subprocess.Popen([str(executable(workspace)), '--ros-args', '--params-file',
                                str(params), '-p', 'model:=edd_symmetric',
                                '-r', f'__ns:=/{namespace}'],
                               env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               text=True, cwd=workspace)
    context = Context()
    rclpy.init(args=[], context=context)
    node = rclpy.create_node('colcon_test_driver', namespace=namespace, context=context)
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    received = []
    publisher = node.create_publisher(JointState, 'joint_states', qos)
    subscription = node.create_subscription(Odometry, 'odom', received.append, qos)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        deadline = time.monotonic() + 20.0
        # Matched both ways (not just on the graph): an answer sent before the node's writer
        # matched our reader would be lost, and the resent sample is a duplicate it does not
        # answer again.
        while (publisher.get_subscription_count() == 0
               or subscription.get_publisher_count() == 0):
            assert process.poll() is None, process.communicate()[0]
            assert time.monotonic() < deadline, 'installed node did not come up'
            executor.spin_once(timeout_sec=0.05)
        t0 = time.time_ns() - 5 * NS_PER_S
        for i in range(6):
            msg = JointState()
            msg.header.stamp = ns_to_stamp(t0 + i * 100_000_000)
            msg.name = ['front_left_wheel_joint', 'rear_left_wheel_joint',
                        'front_right_wheel_joint', 'rear_right_wheel_joint']
            msg.velocity = [2.0, 2.0, 2.0, 2.0]
            until = time.monotonic() + 10.0
            while len(received) <= i and time.monotonic() < until:
                # Resent until answered: the node's best-effort input may still be matching
                # (a repeated stamp is a duplicate for the node: nothing integrated twice).
                publisher.publish(msg)
                spin_until = time.monotonic() + 0.2
                while len(received) <= i and time.monotonic() < spin_until:
                    executor.spin_once(timeout_sec=0.02)
        assert len(received) == 6
        last = received[-1]
        assert last.child_frame_id == 'chassis'
        assert last.twist.twist.linear.x == pytest.approx(0.2 * 0.8 * 2.0, abs=1e-12)
        assert last.pose.pose.position.x == pytest.approx(0.2 * 0.8 * 2.0 * 0.5, abs=1e-9)
    finally:
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        context.try_shutdown()
        process.terminate()
        output = process.communicate(timeout=10)[0]
    assert process.returncode in (0, -15), output
