"""The odometry node in-process: odometry against closed forms, parameters, services, main()."""

import math
from pathlib import Path

from geometry_msgs.msg import PoseWithCovarianceStamped
from node_harness import NodeRig, NS_PER_S, wall_ns
import numpy as np
import pytest
from rcl_interfaces.msg import ParameterType
from rclpy.parameter import Parameter
from skidkin_ros.adapters.bag_reader import open_recording
from skidkin_ros.adapters.bag_writer import BagWriter
from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.config import parameter_schema, write_params_file
from skidkin_ros.core.odometry.integrator import rollout
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.core.rotation import quaternion_to_yaw
from skidkin_ros.errors import ConfigError, ParameterError
from skidkin_ros.node.odom_node import main
from skidkin_ros.node.parameters import check_params_files, parameter_descriptor
from skidkin_ros.node.replay import replay_through_node
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

pytestmark = pytest.mark.ros

R = 0.1651
B = 0.555


def drive(rig, omega_l, omega_r, n=11, dt_ns=20_000_000):
    """Send n samples of constant speed; return (start stamp, duration in s)."""
    t0 = wall_ns() - 5 * NS_PER_S
    for i in range(n):
        rig.send_joint(t0 + i * dt_ns, omega_l, omega_r)
    rig.drain()
    return t0, (n - 1) * dt_ns / NS_PER_S


def planar(msg):
    p = msg.pose.pose
    return p.position.x, p.position.y, quaternion_to_yaw(p.orientation.x, p.orientation.y,
                                                         p.orientation.z, p.orientation.w)


def test_straight_line_matches_closed_form(make_rig):
    rig = make_rig()
    t0, duration_s = drive(rig, 3.0, 3.0)
    last = rig.odom[-1]
    x, y, yaw = planar(last)
    assert x == pytest.approx(R * 3.0 * duration_s, abs=1e-9)
    assert abs(y) < 1e-12 and abs(yaw) < 1e-12
    assert len(rig.odom) == 11  # one per accepted sample
    assert last.header.frame_id == 'odom' and last.child_frame_id == 'base_link'
    assert last.header.stamp.sec * NS_PER_S + last.header.stamp.nanosec == t0 + 200_000_000
    assert last.twist.twist.linear.x == pytest.approx(R * 3.0, abs=1e-12)
    pose_cov = np.array(last.pose.covariance).reshape(6, 6)
    twist_cov = np.array(last.twist.covariance).reshape(6, 6)
    assert np.all(np.diag(pose_cov) > 0) and np.all(np.diag(twist_cov) > 0)


def test_arc_with_params_file_matches_closed_form(make_rig, tmp_path):
    geometry = Geometry(0.2, 0.6)
    values = {'wheel_radius': 0.2, 'track_width': 0.6, 'model': 'edd_symmetric',
              'models.edd_symmetric.alpha': 0.9, 'models.edd_symmetric.b_hat': 0.75,
              'odom_frame_id': 'odom_wheels', 'base_frame_id': 'base_footprint',
              'robot': 'test_bot'}
    path = write_params_file(tmp_path / 'calibrated.yaml', values, {'source': 'test'})
    rig = make_rig(params_file=path)
    assert rig.node.config.model == 'edd_symmetric'
    omega_l, omega_r = 2.0, 4.0
    _, duration_s = drive(rig, omega_l, omega_r, n=26)
    v = geometry.wheel_radius * 0.9 * (omega_l + omega_r) / 2
    w = geometry.wheel_radius * 0.9 * (omega_r - omega_l) / 0.75
    x, y, yaw = planar(rig.odom[-1])
    theta = w * duration_s
    assert yaw == pytest.approx(theta, abs=1e-9)
    assert x == pytest.approx(v / w * math.sin(theta), abs=1e-6)
    assert y == pytest.approx(v / w * (1 - math.cos(theta)), abs=1e-6)
    assert rig.odom[-1].header.frame_id == 'odom_wheels'
    assert rig.odom[-1].child_frame_id == 'base_footprint'


def test_model_switch_with_override_publishes_lateral_velocity(make_rig):
    rig = make_rig({'model': 'full_linear', 'models.full_linear.gamma_21': 0.01,
                    'models.full_linear.gamma_22': 0.03})
    drive(rig, 1.0, 2.0, n=3)
    twist = rig.odom[-1].twist.twist
    assert twist.linear.y == pytest.approx(0.01 * 1.0 + 0.03 * 2.0, abs=1e-12)
    assert twist.linear.x == pytest.approx(R / 2 * 3.0, abs=1e-12)
    assert twist.angular.z == pytest.approx(R / B * 1.0, abs=1e-12)


def test_calibrated_noise_grows_the_pose_covariance(make_rig):
    rig = make_rig({'model': 'edd_symmetric', 'models.edd_symmetric.noise.calibrated': True,
                    'models.edd_symmetric.noise.var_x_per_m': 1e-2})
    drive(rig, 5.0, 5.0, n=21)
    first = np.array(rig.odom[1].pose.covariance).reshape(6, 6)[0, 0]
    last = np.array(rig.odom[-1].pose.covariance).reshape(6, 6)[0, 0]
    distance_m = R * 5.0 * 0.4
    assert last > first > 0
    assert last == pytest.approx(1e-2 * distance_m, rel=0.05)


def test_serialized_and_message_outputs_are_the_same_odometry(make_rig):
    # The node publishes pre-serialized CDR (node/wire.py); the message-object path, used when
    # the serializer disagrees with the middleware, must publish the same thing.
    rig = make_rig({'model': 'edd_symmetric', 'models.edd_symmetric.noise.calibrated': True})
    drive(rig, 2.0, 3.5, n=6)
    serialized = rig.odom[-1]
    rig.node._output.writer_frames, rig.node._output.writer = ('odom', 'base_link'), None
    with rig.node._lock:  # start afresh (a reset would keep the baseline: stamps, speeds)
        rig.node._odometer.clock_changed()
    drive(rig, 2.0, 3.5, n=6)
    assert len(rig.odom) == 12
    assert rig.odom[-1].pose == serialized.pose and rig.odom[-1].twist == serialized.twist
    assert rig.odom[-1].child_frame_id == serialized.child_frame_id == 'base_link'


def test_frame_ids_changed_at_runtime_reach_the_output(make_rig):
    rig = make_rig()
    drive(rig, 1.0, 1.0, n=3)
    assert rig.odom[-1].header.frame_id == 'odom'
    results = rig.node.set_parameters([Parameter('odom_frame_id', value='odom_wheels_long'),
                                       Parameter('base_frame_id', value='b')])
    assert all(r.successful for r in results)
    drive(rig, 1.0, 1.0, n=3)
    assert rig.odom[-1].header.frame_id == 'odom_wheels_long'
    assert rig.odom[-1].child_frame_id == 'b'
    assert rig.odom[-1].twist.twist.linear.x == pytest.approx(R, abs=1e-12)


def test_joint_state_the_reader_refuses_goes_to_rclpy_and_is_counted(make_rig):
    # Data the node's reader does not take (here: a frame_id length that runs past the end) is
    # handed to rclpy's deserialization; what that cannot read is dropped and counted as a
    # malformed message (fault matrix N23). Serialized and message-object input are both taken.
    from rclpy.serialization import serialize_message
    rig = make_rig()
    t0 = wall_ns() - NS_PER_S
    good = bytearray(serialize_message(rig.joint_state(t0, 1.0, 1.0)))
    rig.node._on_joint_state(bytes(good))
    assert rig.node.counters['first'] == 1
    rig.node._on_joint_state(b'\x00\x01\x00\x00' + bytes(8) + b'\xff\xff\x00\x00')
    assert rig.node.counters['malformed_message'] == 1
    assert rig.node.counters['callback_error'] == 0
    rig.node._on_joint_state(rig.joint_state(t0 + 20_000_000, 1.0, 1.0))  # a message object
    assert rig.node.counters['integrated'] == 1


def test_runtime_parameter_changes_validated_and_applied(make_rig):
    rig = make_rig()
    node = rig.node
    result = node.set_parameters([Parameter('wheel_radius', value=-0.1)])[0]
    assert not result.successful
    assert 'wheel_radius' in result.reason and '5' in result.reason  # rclpy's range check
    result = node.set_parameters([Parameter('wheel_radius', value=0.0)])[0]
    assert not result.successful  # the open bound is checked by the node itself
    assert "'wheel_radius'" in result.reason and '(0, 5]' in result.reason
    assert node.get_parameter('wheel_radius').value == R
    result = node.set_parameters([Parameter('models.edd_asymmetric.y_l', value=-1.0)])[0]
    assert not result.successful and 'y_l' in result.reason
    result = node.set_parameters([Parameter('model', value='warp_drive')])[0]
    assert not result.successful and 'ideal_dd' in result.reason
    result = node.set_parameters([Parameter('input', value='wheel_topics')])[0]
    assert not result.successful and 'read-only' in result.reason
    # Accepted: switch model at runtime once its parameters are given (set one at a time:
    # the parameters first); the integrator runs the new one.
    results = node.set_parameters([Parameter('models.edd_symmetric.alpha', value=0.5),
                                   Parameter('model', value='edd_symmetric')])
    assert all(r.successful for r in results), [r.reason for r in results]
    drive(rig, 4.0, 4.0, n=2)
    assert rig.odom[-1].twist.twist.linear.x == pytest.approx(R * 0.5 * 4.0, abs=1e-12)
    # An integer for a float parameter is accepted and converted.
    result = node.set_parameters([Parameter('wheel_radius', value=1)])[0]
    assert result.successful, result.reason
    assert node.config.geometry.wheel_radius == 1.0


def test_integer_for_float_in_yaml_is_accepted(make_rig, tmp_path):
    path = tmp_path / 'ints.yaml'
    path.write_text('/**:\n  ros__parameters:\n    wheel_radius: 1\n    max_dt: 2\n'
                    '    pose_covariance_diagonal: [1, 1, 1, 1, 1, 1]\n')
    rig = make_rig(params_file=path)
    assert rig.node.config.geometry.wheel_radius == 1.0
    assert rig.node.config['max_dt'] == 2.0
    drive(rig, 1.0, 1.0, n=2)
    assert rig.odom[-1].twist.twist.linear.x == pytest.approx(1.0)
    assert list(rig.odom[-1].pose.covariance)[0] == 1.0


@pytest.mark.parametrize('overrides, words', [
    ({'wheel_radius': -0.1}, ['wheel_radius', '(0, 5]']),
    ({'wheel_radius': math.nan}, ['wheel_radius', 'range']),
    ({'max_dt': 'fast'}, ['max_dt', 'number']),
    ({'model': 'warp'}, ['warp', 'edd_symmetric']),
    ({'models.edd_asymmetric.y_l': 0.1, 'models.edd_asymmetric.y_r': -0.0001,
      'models.edd_asymmetric.alpha_l': 1.5}, ['alpha_l', '[0, 1]']),
    ({'left_wheel_joints': 3}, ['left_wheel_joints']),
    ({'wheel_radiuss': 0.2}, ['unknown', 'wheel_radiuss']),
])
def test_startup_refuses_invalid_parameters(overrides, words):
    with pytest.raises(ParameterError) as err:
        NodeRig(overrides)
    for word in words:
        assert word in str(err.value)


def test_y_l_not_above_y_r_refused():
    # y_l > 0 > y_r by range, so a swapped pair is refused naming the parameter and its range.
    with pytest.raises(ParameterError, match=r"'models.edd_asymmetric.y_l' = -0.2 .*\(0, inf\)"):
        NodeRig({'models.edd_asymmetric.y_l': -0.2, 'models.edd_asymmetric.y_r': 0.2})


def test_params_file_of_other_robot_or_schema_refused(tmp_path):
    path = tmp_path / 'other.yaml'
    path.write_text('/**:\n  ros__parameters:\n    robot: warthog\n    expected_robot: husky\n')
    with pytest.raises(ConfigError, match="'warthog'.*'husky'"):
        NodeRig(params_file=path)
    path.write_text('/**:\n  ros__parameters:\n    schema_version: 7\n')
    with pytest.raises(ConfigError, match='schema_version is 7'):
        NodeRig(params_file=path)


def test_descriptors_carry_units_and_finite_ranges():
    schema = {e.name: e for e in parameter_schema()}
    radius = parameter_descriptor(schema['wheel_radius'])
    assert 'm]' in radius.description and radius.floating_point_range[0].to_value == 5.0
    assert radius.dynamic_typing
    x_v = parameter_descriptor(schema['models.edd_asymmetric.x_v'])
    assert not x_v.floating_point_range  # infinite bounds: validated by the node itself
    model = parameter_descriptor(schema['model'])
    assert 'roc' in model.additional_constraints
    assert parameter_descriptor(schema['input']).read_only
    assert model.type in (ParameterType.PARAMETER_NOT_SET, ParameterType.PARAMETER_STRING)


def test_reset_service_and_set_pose(make_rig):
    rig = make_rig()
    drive(rig, 3.0, 3.0, n=5)
    assert rig.node.pose[0] > 0
    assert rig.reset_client.wait_for_service(timeout_sec=5.0)
    future = rig.reset_client.call_async(Trigger.Request())
    rig.spin_until(future.done, what='reset response')
    assert future.result().success
    assert np.all(rig.node.pose == 0.0)
    # set_pose: a valid request sets the pose, a NaN one is rejected and counted (N19).
    msg = PoseWithCovarianceStamped()
    msg.pose.pose.position.x = 2.0
    msg.pose.pose.orientation.z = math.sin(0.25)
    msg.pose.pose.orientation.w = math.cos(0.25)
    rig.set_pose_pub.publish(msg)
    rig.spin_until(lambda: rig.node.counters['set_pose'] == 1, what='set_pose')
    assert rig.node.pose == pytest.approx([2.0, 0.0, 0.5])
    msg.pose.pose.position.y = math.nan
    rig.set_pose_pub.publish(msg)
    rig.spin_until(lambda: rig.node.counters['set_pose_rejected'] == 1, what='rejection')
    assert rig.node.pose == pytest.approx([2.0, 0.0, 0.5])
    assert 'non-finite' in rig.node.last_warnings['set_pose_rejected']
    status = {kv.key: kv.value for kv in rig.node.diagnostic_status().values}
    assert status['count.set_pose_rejected'] == '1'


def test_main_missing_params_file_exits_2(tmp_path, capfd):
    missing = tmp_path / 'nope.yaml'
    assert main(['odom_node', '--ros-args', '--params-file', str(missing)]) == 2
    assert str(missing) in capfd.readouterr().err


def test_params_file_checks_name_the_path(tmp_path):
    broken = tmp_path / 'broken.yaml'
    broken.write_text('/**:\n  ros__parameters: [\n')
    problems = check_params_files(['--ros-args', '--params-file', str(tmp_path),
                                   '--params-file', str(broken), '--params-file'])
    assert len(problems) == 3
    assert str(tmp_path) in problems[0] and 'directory' in problems[0]
    assert str(broken) in problems[1] and 'YAML' in problems[1]
    assert check_params_files(['--ros-args', '-p', 'model:=roc']) == []


def test_main_invalid_parameter_exits_2_with_one_message(capfd):
    code = main(['odom_node', '--ros-args', '-p', 'wheel_radius:=-2.0'])
    err = capfd.readouterr().err
    assert code == 2
    assert "'wheel_radius'" in err and '(0, 5]' in err
    assert 'Traceback' not in err


def test_replay_harness_matches_core_rollout():
    geometry = Geometry(R, B)
    model = get_model('roc').bind({'alpha': 0.95, 'beta_1': 0.4, 'beta_2': 0.1}, geometry)
    n = 400
    t_ns = np.arange(n, dtype=np.int64) * 20_000_000  # starts at 0: the harness shifts it
    rng = np.random.default_rng(3)
    omega_l = np.cumsum(rng.normal(0, 0.2, n)) + 2.0
    omega_r = np.cumsum(rng.normal(0, 0.2, n)) + 3.0
    samples = WheelSamples(t_ns, omega_l, omega_r)
    result = replay_through_node(samples, overrides={
        'model': 'roc', 'models.roc.alpha': 0.95, 'models.roc.beta_1': 0.4,
        'models.roc.beta_2': 0.1}, left_joints=['l'], right_joints=['r1', 'r2'])
    # interval ending (the default): sample k's speeds over [t_k-1, t_k]
    expected = rollout(model.twist(omega_l[1:], omega_r[1:]), np.diff(t_ns) * 1e-9)
    assert len(result) == n
    assert np.array_equal(result.t_ns, t_ns)
    np.testing.assert_allclose(result.poses, expected, atol=1e-9)
    np.testing.assert_allclose(result.vx, model.twist(omega_l, omega_r)[:, 0], atol=1e-12)
    assert result.pose_cov.shape == (n, 6, 6) and result.counters['integrated'] == n - 1


def test_example_config_loads_as_is(make_rig):
    path = Path(__file__).resolve().parents[1] / 'config' / 'odom_node.yaml'
    rig = make_rig(params_file=path)
    config = rig.node.config
    assert config.geometry == Geometry(0.1651, 0.555) and config['robot'] == 'husky_a200'
    assert config['left_wheel_joints'] == ['front_left_wheel_joint', 'rear_left_wheel_joint']
    drive(rig, 1.0, 1.0, n=2)
    assert len(rig.odom) == 2


def _float64_drive():
    """Return (side, receive ns, rad/s) of two Float64 wheel topics as drivers send them.

    Staggered sides with jitter, a turn, one right message lost (a left value left unpaired),
    a NaN and a pause longer than max_dt.
    """
    rng = np.random.default_rng(3)
    events = []
    t_ns = 100 * NS_PER_S
    for i in range(40):
        omega = 2.0 + 0.05 * i
        t_ns += int(rng.integers(15, 25) * 1e6) + (int(0.8 * NS_PER_S) if i == 25 else 0)
        events.append(('left', t_ns, math.nan if i == 12 else omega))
        if i != 7:
            events.append(('right', t_ns + int(rng.integers(1, 9) * 1e6), 1.5 * omega))
    return events


def test_float64_bag_replayed_through_the_node_reproduces_predict(make_rig, tmp_path):
    """Offline, two Float64 topics are paired by the node's own rule: same samples, same poses."""
    events = _float64_drive()
    with BagWriter(tmp_path / 'bag') as bag:
        for side, t_ns, omega in events:
            bag.write_float64(f'/wheel/{side}/velocity', t_ns, omega)
    with open_recording(tmp_path / 'bag') as bag:
        wheels = bag.read_wheels(left_topic='/wheel/left/velocity',
                                 right_topic='/wheel/right/velocity')
    rig = make_rig({'input': 'wheel_topics', 'use_sim_time': True, 'model': 'edd_symmetric',
                    'models.edd_symmetric.alpha': 0.9, 'models.edd_symmetric.b_hat': 0.7})
    for side, t_ns, omega in events:  # as `ros2 bag play --clock` would, one message at a time
        rig.publish_clock(t_ns)
        rig.send(Float64(data=omega), rig.left_pub if side == 'left' else rig.right_pub)
    rig.drain()
    expected = Odometer.from_config(rig.node.config).predict(wheels)
    published = expected.accepted & np.array([s.value != 'duplicate' for s in expected.status])
    stamps = [m.header.stamp.sec * NS_PER_S + m.header.stamp.nanosec for m in rig.odom]
    assert stamps == expected.t_ns[published].tolist()
    assert rig.node.counters['unpaired'] == 1 and rig.node.counters['non_finite'] == 1
    assert rig.node.counters['gap'] == 1
    node = np.array([planar(m) for m in rig.odom])
    assert np.array_equal(node[:, :2], expected.poses[published, :2])  # bit for bit
    np.testing.assert_allclose(node[:, 2], expected.poses[published, 2], rtol=0, atol=1e-15)
    assert np.array_equal([m.twist.twist.angular.z for m in rig.odom],
                          expected.twists[published, 2])


def test_params_file_the_offline_tools_refuse_stops_the_node_and_a_duplicate_warns(tmp_path,
                                                                                   capfd):
    """N33: an empty file started the node with Husky defaults."""
    empty = tmp_path / 'empty.yaml'
    empty.write_text('# nothing here\n')
    assert main(['odom_node', '--ros-args', '--params-file', str(empty)]) == 2
    err = capfd.readouterr().err
    assert str(empty) in err and 'empty' in err and 'Traceback' not in err
    bomb = tmp_path / 'bomb.yaml'
    bomb.write_text('a: &a [1.0, 1.0]\n/**:\n  ros__parameters:\n    max_dt: *a\n')
    problems = check_params_files(['--ros-args', '--params-file', str(bomb)])
    assert len(problems) == 1 and 'alias *a is not allowed' in problems[0]
    dup = tmp_path / 'dup.yaml'
    dup.write_text('/**:\n  ros__parameters:\n    max_dt: 0.3\n    max_dt: 0.4\n')
    warnings = []
    assert check_params_files(['--ros-args', '--params-file', str(dup)], warnings) == []
    assert warnings == [f"parameters file {dup}: key 'max_dt' is given twice (line 4); the last "
                        'value wins']
