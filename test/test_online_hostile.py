"""Online calibration met by a hostile publisher and a careless user: refused, said, never stuck.

Each test drives real parts (the odometer, the rclpy node, a bag written with rosbags and the
CLI) with one input a field robot meets: a reference stamp hours ahead, a clock that jumps back
(a bag replayed in a loop), quaternions that are not unit, a save path typed as a user types it,
frames configured for a recording read offline.
"""

import csv
import math
import time

from nav_msgs.msg import Odometry
from node_harness import NodeRig, RELIABLE
import numpy as np
import pytest
from rclpy.parameter import Parameter
from skidkin_ros.adapters.bag_writer import BagWriter
from skidkin_ros.cli.main import main
from skidkin_ros.core.odometry.config import OdometryConfig, write_params_file
from skidkin_ros.core.online import online_odometer
from skidkin_ros.core.rotation import quaternion_to_yaw, yaw_to_quaternion
from skidkin_ros.node.conversions import ns_to_stamp
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, JOINT_NAMES, SimConfig, simulate
from std_srvs.srv import Trigger

FILE = {'model': 'edd_asymmetric', 'robot': 'sim',
        **{f'models.edd_asymmetric.{k}': v for k, v in DEFAULT_TRUE_PARAMS.items()},
        'models.edd_asymmetric.noise.calibrated': True, 'online.enabled': True}
HOURS_3_NS = 3 * 3600 * 1_000_000_000


def _stream(odometer, sim, rows, arrival=None):
    """Feed wheel samples and reference rows (t, x, y, yaw[, frame, child]) in arrival order.

    ``arrival``: each row's arrival on the wheel clock (default: its stamp).
    """
    arrival = [row[0] for row in rows] if arrival is None else arrival
    odometer.reset()
    poses, j = [], 0
    for t, left, right in zip(sim.wheels.t_ns.tolist(), sim.wheels.omega_l, sim.wheels.omega_r):
        while j < len(rows) and arrival[j] <= t:
            odometer.reference_sample(*rows[j])
            j += 1
        poses.append(odometer.step(t, left, right).pose)
    return np.array(poses)


def _rows(sim, period_ns=100_000_000):
    track = sim.truth_at(np.arange(sim.start_ns, sim.end_ns, period_ns))
    return list(zip(track.t_ns.tolist(), track.x.tolist(), track.y.tolist(),
                    track.yaw.tolist()))


def test_n176_a_reference_stamped_hours_ahead_is_refused_and_learning_goes_on():
    sim = simulate(SimConfig(duration_s=40.0, seed=31))
    rows = _rows(sim)
    clean = online_odometer(OdometryConfig.from_flat(FILE))
    expected = _stream(clean, sim, rows)
    assert clean.counters['online_segments'] >= 8
    hostile = rows[:60] + [(rows[59][0] + HOURS_3_NS, *rows[59][1:])] + rows[60:200] + [
        ((2 ** 31 - 1) * 1_000_000_000, *rows[199][1:])] + rows[200:]
    said = []
    odometer = online_odometer(OdometryConfig.from_flat(FILE),
                               warn=lambda cause, message, error=False: said.append(message))
    # each arrives with its neighbours (a publisher's clock glitch)
    poses = _stream(odometer, sim, hostile, [row[0] for row in rows[:60]] + [rows[59][0]]
                    + [row[0] for row in rows[60:200]] + [rows[199][0]]
                    + [row[0] for row in rows[200:]])
    # before: the pose 3 h ahead was accepted and every later one refused as older
    assert odometer.counters['reference_future'] == 2
    assert odometer.counters['reference_older'] == 0
    assert odometer.counters['online_segments'] == clean.counters['online_segments']
    assert np.array_equal(poses, expected)
    assert odometer.learner.state() == 'learning'
    assert any('10800.' in m and 's ahead of the last wheel sample' in m for m in said), said


def _reference_msg(t_ns, x, y, q, frame='odom_lidar', child='base_link'):
    msg = Odometry()
    msg.header.stamp = ns_to_stamp(t_ns)
    msg.header.frame_id = frame
    msg.child_frame_id = child
    msg.pose.pose.position.x = float(x)
    msg.pose.pose.position.y = float(y)
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in q)
    return msg


def _drive_node(rig, ref_pub, t0_ns, n, quaternion=yaw_to_quaternion):
    """Send n wheel samples at 20 Hz (a left turn) and a reference pose every second one.

    Returns the (t, x, y, yaw) rows sent, the yaw as the wire carries it.
    """
    r, b = 0.1651, 0.555
    omega_l, omega_r = 2.0, 3.0
    v, w = 0.5 * r * (omega_l + omega_r), r * (omega_r - omega_l) / b
    rows = []
    for i in range(n):
        t = t0_ns + i * 50_000_000
        rig.send_joint(t, omega_l, omega_r)
        if i % 2 == 0:
            s = i * 0.05
            yaw = w * s
            x, y = v / w * math.sin(yaw), v / w * (1.0 - math.cos(yaw))
            before = rig.node.counters['reference_received']
            ref_pub.publish(_reference_msg(t, x, y, quaternion(yaw)))
            rig.spin_until(lambda: rig.node.counters['reference_received'] > before,
                           what='reference pose')
            rows.append((t, x, y, quaternion_to_yaw(*yaw_to_quaternion(yaw))))
    rig.drain()
    return rows


@pytest.mark.ros
def test_n177_learning_resumes_after_the_clock_jumps_back():
    rig = NodeRig({**FILE, 'use_sim_time': True})
    try:
        ref_pub = rig.driver.create_publisher(Odometry, 'reference/odom', RELIABLE)
        rig.wait_matched(ref_pub)
        t0 = 1_000 * 1_000_000_000
        rig.publish_clock(t0 + 10 * 1_000_000_000)
        _drive_node(rig, ref_pub, t0, 160)
        first = rig.node.counters['reference_accepted']
        assert first >= 70 and rig.node.counters['online_segments'] >= 2
        # the bag starts again: the clock jumps back, the node resets (N12), the same stamps
        rig.publish_clock(t0 - 1_000_000_000)
        rig.spin_until(lambda: rig.node.counters['clock_jump'] >= 1, what='clock jump')
        rig.publish_clock(t0 + 10 * 1_000_000_000)
        segments = rig.node.counters['online_segments']
        _drive_node(rig, ref_pub, t0, 160)
        # before: every pose of the second pass was refused as older than the first pass's
        assert rig.node.counters['reference_older'] == 0
        assert rig.node.counters['reference_accepted'] - first >= 70
        assert rig.node.counters['online_segments'] > segments
    finally:
        rig.close()


def test_a_quaternion_that_is_not_unit_gives_its_rotations_yaw():
    for yaw in (-3.0, -1.2, 0.0, 0.4, 1.57, 3.1):
        q = np.array(yaw_to_quaternion(yaw))
        assert quaternion_to_yaw(*q) == pytest.approx(yaw, abs=1e-12)
        for scale in (1e-3, 0.5, 1.01, 7.0):
            assert quaternion_to_yaw(*(scale * q)) == pytest.approx(yaw, abs=1e-12)
    # a unit quaternion's yaw is bit for bit the formula's, as before
    q = yaw_to_quaternion(0.7)
    assert quaternion_to_yaw(*q) == math.atan2(2.0 * (q[3] * q[2]), 1.0 - 2.0 * q[2] * q[2])
    for bad in ((0.0, 0.0, 0.0, 0.0), (math.nan, 0.0, 0.0, 1.0), (0.0, 0.0, math.inf, 1.0)):
        assert math.isnan(quaternion_to_yaw(*bad))


@pytest.mark.ros
def test_n178_zero_and_unnormalized_reference_quaternions():
    rig = NodeRig(FILE)
    try:
        ref_pub = rig.driver.create_publisher(Odometry, 'reference/odom', RELIABLE)
        rig.wait_matched(ref_pub)
        t0 = time.time_ns() - 60 * 1_000_000_000
        # a relay that drops the normalisation: every quaternion scaled by 0.5
        rows = _drive_node(rig, ref_pub, t0, 160,
                           lambda yaw: tuple(0.5 * v for v in yaw_to_quaternion(yaw)))
        counters = rig.node.counters
        assert counters['reference_accepted'] >= 79 and counters['online_segments'] >= 2
        # the node learned what the unit quaternions teach
        odometer = online_odometer(OdometryConfig.from_flat(FILE))
        odometer.reset()
        j = 0
        for i in range(160):
            t = t0 + i * 50_000_000
            while j < len(rows) and rows[j][0] <= t:
                odometer.reference_sample(*rows[j])
                j += 1
            odometer.step(t, 2.0, 3.0)
        learned = rig.node._odometer.learner.values
        # the changes of ground the unit quaternions make, no more (before: 3-4 false ones)
        assert counters['online_change'] == odometer.counters['online_change'] <= 1
        for name, value in odometer.learner.values.items():
            assert learned[name] == pytest.approx(value, rel=1e-6, abs=1e-8), name
        # a zero quaternion (an unset orientation) has no heading: refused, never yaw 0
        before = counters['reference_non_finite']
        published = counters['published']
        t = t0 + 160 * 50_000_000
        rig.send_joint(t, 2.0, 3.0)
        ref_pub.publish(_reference_msg(t, 1.0, 1.0, (0.0, 0.0, 0.0, 0.0)))
        rig.spin_until(lambda: counters['reference_non_finite'] > before, what='refusal')
        rig.drain()
        assert counters['published'] == published + 1
        assert all(np.all(np.isfinite(m.pose.covariance)) for m in rig.odom)
    finally:
        rig.close()


def _save(rig, client):
    future = client.call_async(Trigger.Request())
    rig.spin_until(future.done, what='save_calibration')
    return future.result()


@pytest.mark.ros
def test_n179_save_calibration_where_a_user_points_it(tmp_path, monkeypatch):
    home = tmp_path / 'home'
    home.mkdir()
    monkeypatch.setenv('HOME', str(home))
    monkeypatch.chdir(tmp_path)
    rig = NodeRig({**FILE, 'online.save_path': '~/learned.yaml'})
    try:
        client = rig.driver.create_client(Trigger, 'odom_node/save_calibration')
        assert client.wait_for_service(timeout_sec=5.0)
        # '~' as typed in `-p online.save_path:=~/learned.yaml` (no shell expands it there)
        answer = _save(rig, client)
        assert answer.success, answer.message
        assert OdometryConfig.from_file(home / 'learned.yaml').online.enabled
        assert not (tmp_path / '~').exists()

        def save_to(path):
            rig.node.set_parameters([Parameter('online.save_path', value=str(path))])
            return _save(rig, client)
        for path, words in ((tmp_path / 'nowhere' / 'x.yaml', 'does not exist'),
                            (tmp_path, 'is a folder'),
                            ('./home/../home/learned.yaml', 'never overwritten')):
            answer = save_to(path)
            assert not answer.success, path
            # said in the node's terms: no CLI option the node does not have
            assert 'online.save_path' in answer.message and words in answer.message, path
            assert '--out' not in answer.message and '--force' not in answer.message, path
        # no save_path: a name from the UTC time; twice in one second, two files
        answers = [save_to(''), save_to('')]
        assert all(a.success for a in answers), [a.message for a in answers]
        saved = sorted(tmp_path.glob('skidkin_online_*.yaml'))
        assert len(saved) == 2
        for path in saved:
            OdometryConfig.from_file(path)
        assert rig.node.counters['save_refused'] == 3
    finally:
        rig.close()


def _two_frame_bag(tmp_path, sim):
    """Write a bag whose reference topic carries a second publisher's poses: 'map', 0.3 m off."""
    path = tmp_path / 'drive'
    rows = []
    with BagWriter(path) as writer:
        reference = sim.truth_at(np.arange(sim.start_ns, sim.end_ns, 50_000_000))
        j = 0
        for i, t in enumerate(sim.wheels.t_ns.tolist()):
            while j < len(reference) and reference.t_ns[j] <= t:
                frame = 'map' if j % 2 else 'odom_lidar'
                x = reference.x[j] + (0.3 if j % 2 else 0.0)
                stamp = int(reference.t_ns[j])
                writer.write_odometry('/ref', stamp, frame, 'base_link', x,
                                      reference.y[j], reference.yaw[j])
                yaw = quaternion_to_yaw(*yaw_to_quaternion(float(reference.yaw[j])))
                rows.append((stamp, float(x), float(reference.y[j]), yaw, frame, 'base_link'))
                j += 1
            writer.write_joint_state('/joint_states', t, JOINT_NAMES,
                                     [sim.wheels.omega_l[i]] * 2 + [sim.wheels.omega_r[i]] * 2)
    return path, rows


def test_c275_predict_applies_the_reference_frames_of_the_parameters_file(tmp_path, capsys):
    sim = simulate(SimConfig(duration_s=30.0, seed=33))
    bag, rows = _two_frame_bag(tmp_path, sim)
    flat = {**FILE, 'online.reference_frame_id': 'odom_lidar'}
    params = write_params_file(tmp_path / 'file.yaml', flat, {'source': 'test'})
    out = tmp_path / 'pred.csv'
    assert main(['predict', str(bag), '--params', str(params), '--reference', '/ref',
                 '--out', str(out)]) == 0
    # the node's rule: poses in 'map' refused on arrival (the node's odometer, fed the frames)
    odometer = online_odometer(OdometryConfig.from_file(params))
    expected = _stream(odometer, sim, rows)
    assert odometer.counters['reference_frame'] == len(rows) // 2
    assert odometer.counters['online_segments'] >= 5
    with out.open() as handle:
        got = np.array([[float(r['x']), float(r['y'])] for r in csv.DictReader(handle)])
    # before: predict read no frame and refused every pose (nothing learned)
    np.testing.assert_allclose(got, expected[:, :2], rtol=0, atol=1e-9)
    assert f'{odometer.counters["online_segments"]} segments' in capsys.readouterr().out
    # a frame no pose has: said, with the frames the topic has
    none = write_params_file(tmp_path / 'none.yaml', {**FILE, 'online.reference_frame_id':
                                                      'odom'}, {'source': 'test'})
    assert main(['predict', str(bag), '--params', str(none), '--reference', '/ref',
                 '--out', str(tmp_path / 'none.csv')]) == 0
    said = capsys.readouterr().out
    assert 'no pose on /ref is in the configured frames' in said and "'map'" in said


@pytest.mark.ros
def test_n177_two_publishers_in_two_frames_on_one_topic_are_said():
    for configured in (False, True):
        flat = {**FILE, 'online.reference_frame_id': 'odom_lidar'} if configured else FILE
        rig = NodeRig(flat)
        try:
            ref_pub = rig.driver.create_publisher(Odometry, 'reference/odom', RELIABLE)
            other = rig.driver.create_publisher(Odometry, 'reference/odom', RELIABLE)
            rig.wait_matched(ref_pub)
            rig.wait_matched(other)
            t0 = time.time_ns() - 60 * 1_000_000_000
            rows = _drive_node(rig, ref_pub, t0, 40)
            for t, x, y, yaw in rows[1:]:   # a second localiser, 0.2 m off, in 'map'
                before = rig.node.counters['reference_received']
                other.publish(_reference_msg(t + 25_000_000, x + 0.2, y,
                                             yaw_to_quaternion(yaw), frame='map'))
                rig.spin_until(lambda: rig.node.counters['reference_received'] > before,
                               what='reference pose')
            warned = rig.node.last_warnings.get('reference_frames_mixed', '')
            if configured:   # the frame rule refuses 'map': nothing to say beyond the count
                assert warned == '' and rig.node.counters['reference_frame'] == len(rows) - 1
            else:   # before: nothing said, both learned from
                assert "'map'" in warned and 'online.reference_frame_id' in warned
        finally:
            rig.close()


def test_c276_a_robot_carried_with_its_wheels_still_declares_no_grounds():
    sim = simulate(SimConfig(duration_s=90.0, seed=44))
    wheels, rows = sim.wheels, _rows(sim)
    lifted, set_down = wheels.t_ns[0] + 30 * 1_000_000_000, wheels.t_ns[0] + 55 * 1_000_000_000
    still = (wheels.t_ns >= lifted) & (wheels.t_ns < set_down)
    carried = type(wheels)(wheels.t_ns, np.where(still, 0.0, wheels.omega_l),
                           np.where(still, 0.0, wheels.omega_r))
    odometer = online_odometer(OdometryConfig.from_flat(FILE))
    poses = odometer.predict(carried, reference=sim.truth_at(np.array([r[0] for r in rows])))
    assert np.all(np.isfinite(poses.poses))
    learner = odometer.learner
    # 25 s carried: the wheels say nothing about the ground (before: 30-34 'changes of ground'
    # and the bank full of 4 grounds, remembered ones forgotten); the straddling segment at
    # most one
    assert odometer.counters['online_wheels_still'] >= 20
    assert odometer.counters['online_change'] <= 1 and len(learner.grounds) <= 2
    for name, value in learner.values.items():
        assert value == pytest.approx(DEFAULT_TRUE_PARAMS[name], rel=0.03), name
