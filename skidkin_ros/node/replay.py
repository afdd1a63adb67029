"""Run the real odometry node in-process on recorded wheel samples and collect its output.

The node is the same :class:`~skidkin_ros.node.odom_node.OdomNode` that ``ros2 run`` starts, with
real rclpy and real DDS, in a private rclpy context and a unique namespace. Samples go in as
sensor_msgs/JointState; the node's input and output QoS are switched to reliable with deep
queues through the standard ``qos_overrides`` parameters and the harness sends samples in
windows, waiting until the node has taken each window, so no message is dropped.

Example::

    from skidkin_ros.node.replay import replay_through_node
    result = replay_through_node(drive.wheels, params_file=Path('calibrated.yaml'))
    print(result.x[-1], result.y[-1], result.yaw[-1])
"""

from __future__ import annotations

from dataclasses import dataclass, field
import itertools
import math
import os
from pathlib import Path
import time
from typing import Any, Callable, Mapping, Sequence

from nav_msgs.msg import Odometry
import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Imu, JointState
from skidkin_ros.core.drive import ImuSamples, PoseTrack, WheelSamples
from skidkin_ros.core.rotation import quaternion_to_yaw, yaw_to_quaternion
from skidkin_ros.core.timeunits import NS_PER_S
from skidkin_ros.errors import SkidkinError
from skidkin_ros.node.conversions import ns_to_stamp, stamp_to_ns
from skidkin_ros.node.odom_node import OdomNode

__all__ = ['ReplayResult', 'ReplayError', 'replay_through_node']

WINDOW = 64            # samples in flight at once; well below the queue depths set below
QUEUE_DEPTH = 1024
_instance = itertools.count()


class ReplayError(SkidkinError):
    """The node did not take or answer the replayed samples in time."""


@dataclass(frozen=True)
class ReplayResult:
    """Odometry published by the node, one row per message (in publication order).

    ``t_ns`` is the odometry stamp in the time base of the input samples; ``yaw`` is unwrapped
    (continuous) from the published quaternions; ``pose_cov`` and ``twist_cov`` are (N, 6, 6).
    ``counters`` is the node's per-cause sample counters at the end (see /diagnostics).
    """

    t_ns: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    wz: np.ndarray
    pose_cov: np.ndarray
    twist_cov: np.ndarray
    counters: Mapping[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t_ns.size)

    @property
    def poses(self) -> np.ndarray:
        """Return the poses as an (N, 3) array of x, y and unwrapped yaw."""
        return np.stack([self.x, self.y, self.yaw], axis=-1)


def _result(messages: Sequence[Odometry], offset_ns: int,
            counters: Mapping[str, int]) -> ReplayResult:
    n = len(messages)
    t_ns = np.array([stamp_to_ns(m.header.stamp) - offset_ns for m in messages], dtype=np.int64)
    x = np.array([m.pose.pose.position.x for m in messages], dtype=float)
    y = np.array([m.pose.pose.position.y for m in messages], dtype=float)
    yaw = np.array([quaternion_to_yaw(m.pose.pose.orientation.x, m.pose.pose.orientation.y,
                                      m.pose.pose.orientation.z, m.pose.pose.orientation.w)
                    for m in messages], dtype=float)
    yaw = np.unwrap(yaw) if n else yaw
    vx = np.array([m.twist.twist.linear.x for m in messages], dtype=float)
    vy = np.array([m.twist.twist.linear.y for m in messages], dtype=float)
    wz = np.array([m.twist.twist.angular.z for m in messages], dtype=float)
    pose_cov = np.array([np.asarray(m.pose.covariance).reshape(6, 6) for m in messages],
                        dtype=float).reshape(n, 6, 6)
    twist_cov = np.array([np.asarray(m.twist.covariance).reshape(6, 6) for m in messages],
                         dtype=float).reshape(n, 6, 6)
    return ReplayResult(t_ns, x, y, yaw, vx, vy, wz, pose_cov, twist_cov, dict(counters))


def _stamp_offset(samples: WheelSamples, stamp_offset_ns: int | None) -> int:
    """Shift stamps so none is zero or negative (a zero stamp is rejected by the node)."""
    if stamp_offset_ns is not None:
        return int(stamp_offset_ns)
    if len(samples) and int(samples.t_ns[0]) <= 0:
        return NS_PER_S - int(samples.t_ns[0])
    return 0


def _joint_state(names: list[str], n_left: int, t_ns: int, omega_l: float,
                 omega_r: float, position: tuple[float, float] | None = None) -> JointState:
    """Return one JointState: each side's speed (and position, if given) on all its joints."""
    n_right = len(names) - n_left
    msg = JointState()
    msg.header.stamp = ns_to_stamp(t_ns)
    msg.name = names
    msg.velocity = [float(omega_l)] * n_left + [float(omega_r)] * n_right
    if position is not None:
        msg.position = [float(position[0])] * n_left + [float(position[1])] * n_right
    return msg


Side = tuple[np.ndarray, Callable[[int], None], bool]


def _send_interleaved(harness: '_Harness', samples: WheelSamples, names: list[str], n_left: int,
                      offset_ns: int, deadline: float,
                      positions: Sequence[tuple[float, float] | None] | None,
                      sides: Sequence[Side]) -> None:
    """Send wheel samples and side streams (gyro, reference) merged in stamp order.

    ``sides``: (stamps, send one, send the rest) per stream, in the order ``Odometer.predict``
    hands them over: before a wheel sample, each stream's messages stamped up to its stamp (the
    gyro's, then the reference's); each message is sent only once the node took the one before.
    A stream's third item: its messages after the last wheel sample are sent too.
    """
    counters = harness.odom.counters
    next_of = [0] * len(sides)
    for i in range(len(samples)):
        t_wheel = int(samples.t_ns[i])
        for s, (side_t, send_side, _) in enumerate(sides):
            j = next_of[s]
            while j < side_t.size and side_t[j] <= t_wheel:
                send_side(j)
                j += 1
            next_of[s] = j
        target = counters['received'] + 1
        harness.publisher.publish(_joint_state(names, n_left, t_wheel + offset_ns,
                                               samples.omega_l[i], samples.omega_r[i],
                                               None if positions is None else positions[i]))
        harness.spin_until(lambda: counters['received'] >= target,
                           max(deadline - time.monotonic(), 0.0), f'wheel sample {i}')
    for (side_t, send_side, send_rest), j in zip(sides, next_of):
        if send_rest:
            for k in range(j, side_t.size):
                send_side(k)


def _gyro_side(harness: '_Harness', imu: ImuSamples, offset_ns: int, deadline: float) -> Side:
    """Return the gyro stream of :func:`_send_interleaved` (the node subscribed to it)."""
    harness.spin_until(lambda: harness.imu_publisher.get_subscription_count() > 0,
                       max(deadline - time.monotonic(), 0.0), 'the node to subscribe to imu')
    counters = harness.odom.counters
    gyro_t = np.asarray(imu.t_ns, dtype=np.int64)

    def send_gyro(k: int) -> None:
        msg = Imu()
        msg.header.stamp = ns_to_stamp(int(gyro_t[k]) + offset_ns)
        msg.angular_velocity.z = float(imu.yaw_rate[k])
        target = counters['imu_received'] + 1
        harness.imu_publisher.publish(msg)
        harness.spin_until(lambda: counters['imu_received'] >= target,
                           max(deadline - time.monotonic(), 0.0), f'gyro sample {k}')
    # the gyro samples after the last wheel sample release the samples still waiting
    return gyro_t, send_gyro, True


def _send_with_imu(harness: '_Harness', samples: WheelSamples, imu: ImuSamples,
                   names: list[str], n_left: int, offset_ns: int, deadline: float,
                   positions: Sequence[tuple[float, float] | None] | None) -> None:
    """Send wheel and gyro samples merged in stamp order, waiting for the node to take each.

    ``positions`` as :func:`replay_through_node` takes them (fault matrix N70: they were
    dropped when a gyro was replayed too).
    """
    _send_interleaved(harness, samples, names, n_left, offset_ns, deadline, positions,
                      [_gyro_side(harness, imu, offset_ns, deadline)])


def _reference_msg(t_ns: int, x: float, y: float, yaw: float, frame_id: str,
                   child_frame_id: str, yaw_variance: float = math.nan) -> Odometry:
    msg = Odometry()
    if math.isfinite(yaw_variance):   # the heading's variance, as the recording had it
        msg.pose.covariance[35] = float(yaw_variance)
    msg.header.stamp = ns_to_stamp(t_ns)
    msg.header.frame_id = frame_id
    msg.child_frame_id = child_frame_id
    msg.pose.pose.position.x = float(x)
    msg.pose.pose.position.y = float(y)
    qx, qy, qz, qw = yaw_to_quaternion(float(yaw))
    msg.pose.pose.orientation.z = qz
    msg.pose.pose.orientation.w = qw
    return msg


def _send_with_reference(harness: '_Harness', samples: WheelSamples, reference: PoseTrack,
                         names: list[str], n_left: int, offset_ns: int, deadline: float,
                         frames: tuple[str, str], imu: ImuSamples | None = None,
                         positions: Sequence[tuple[float, float] | None] | None = None) -> None:
    """Send wheel samples and reference poses (and gyro samples) in stamp order, one at a time.

    A reference pose stamped up to a wheel sample's stamp goes first (after the gyro samples up
    to it), as ``Odometer.predict`` hands them over; the yaw goes through a quaternion, as on
    the wire.
    """
    harness.spin_until(lambda: harness.reference_publisher.get_subscription_count() > 0,
                       max(deadline - time.monotonic(), 0.0), 'the node to subscribe to the '
                       'reference')
    counters = harness.odom.counters
    ref_t = np.asarray(reference.t_ns, dtype=np.int64)
    variance = (np.full(len(ref_t), np.nan) if reference.yaw_variance is None
                else reference.yaw_variance)

    def send_reference(k: int) -> None:
        target = counters['reference_received'] + 1
        harness.reference_publisher.publish(_reference_msg(
            int(ref_t[k]) + offset_ns, reference.x[k], reference.y[k], reference.yaw[k],
            *frames, float(variance[k])))
        harness.spin_until(lambda: counters['reference_received'] >= target,
                           max(deadline - time.monotonic(), 0.0), f'reference pose {k}')

    sides = [] if imu is None else [_gyro_side(harness, imu, offset_ns, deadline)]
    _send_interleaved(harness, samples, names, n_left, offset_ns, deadline, positions,
                      sides + [(ref_t, send_reference, False)])


class _Harness:
    """The node under test, a driver node and one executor in a private context."""

    def __init__(self, context: Context, namespace: str, params_file: Path | None,
                 overrides: Mapping[str, Any]) -> None:
        cli_args = ['--ros-args', '--params-file', str(params_file)] if params_file else None
        self.odom = OdomNode(context=context, namespace=namespace, cli_args=cli_args,
                             use_global_arguments=False, enable_rosout=False,
                             parameter_overrides=[Parameter(k, value=v)
                                                  for k, v in overrides.items()])
        self.driver = rclpy.create_node('skidkin_replay_driver', namespace=namespace,
                                        context=context, use_global_arguments=False,
                                        enable_rosout=False, start_parameter_services=False)
        qos = QoSProfile(depth=QUEUE_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
        self.publisher = self.driver.create_publisher(JointState, 'joint_states', qos)
        self.imu_publisher = self.driver.create_publisher(Imu, 'imu/data', qos)
        self.reference_publisher = self.driver.create_publisher(Odometry, 'reference/odom', qos)
        self.received: list[Odometry] = []
        self.driver.create_subscription(Odometry, 'odom', self.received.append, qos)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.odom)
        self.executor.add_node(self.driver)

    def spin_until(self, done, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while not done():
            if time.monotonic() > deadline:
                raise ReplayError(f'replay: timed out after {timeout_s:g} s waiting for {what}')
            self.executor.spin_once(timeout_sec=0.01)

    def connected(self) -> bool:
        return (self.publisher.get_subscription_count() > 0
                and self.odom._output.publisher.get_subscription_count() > 0)

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.odom.destroy_node()
        self.driver.destroy_node()


def replay_through_node(samples: WheelSamples, params_file: Path | None = None,
                        overrides: Mapping[str, Any] | None = None,
                        left_joints: Sequence[str] | None = None,
                        right_joints: Sequence[str] | None = None,
                        timeout_s: float = 60.0,
                        stamp_offset_ns: int | None = None,
                        positions: Sequence[tuple[float, float] | None] | None = None,
                        imu: ImuSamples | None = None, reference: PoseTrack | None = None,
                        reference_frames: tuple[str, str] = ('', '')) -> ReplayResult:
    """Feed ``samples`` to a real OdomNode as JointState messages and return its odometry.

    ``params_file`` and ``overrides`` (flat parameter names, e.g. ``{'model': 'roc'}``) configure
    the node as ``--params-file`` and ``-p`` would; the input is forced to ``joint_state``.
    Joint names default to the node's ``left_wheel_joints`` / ``right_wheel_joints``. Stamps are
    shifted by ``stamp_offset_ns`` (default: only when the first stamp is <= 0, which the node
    would reject as unset) and shifted back in the result. ``timeout_s`` bounds the whole run.
    ``positions``: per sample, the (left, right) joint positions (rad) the messages carry, or
    None for a message without positions (default: none carries any).
    ``imu``: gyro samples sent as sensor_msgs/Imu on imu/data (for imu.mode adapt or fuse), in
    stamp order with the wheel samples (a gyro sample before a wheel sample of the same stamp)
    and one message at a time, so the node takes them in the order ``Odometer.predict`` does.
    ``reference``: poses sent as nav_msgs/Odometry on reference/odom (online.enabled), in stamp
    order with the wheel samples, with ``reference_frames`` (frame_id, child_frame_id).
    Raises ConfigError if the node refuses the configuration, ReplayError on a timeout.
    """
    params = dict(overrides or {})
    params['input'] = 'joint_state'
    if left_joints is not None:
        params['left_wheel_joints'] = list(left_joints)
    if right_joints is not None:
        params['right_wheel_joints'] = list(right_joints)
    namespace = f'/skidkin_replay_{os.getpid()}_{next(_instance)}'
    for topic, role in (('joint_states', 'subscription'), ('odom', 'publisher'),
                        ('imu/data', 'subscription'), ('reference/odom', 'subscription')):
        params[f'qos_overrides.{namespace}/{topic}.{role}.reliability'] = 'reliable'
        params[f'qos_overrides.{namespace}/{topic}.{role}.depth'] = QUEUE_DEPTH
    offset_ns = _stamp_offset(samples, stamp_offset_ns)
    deadline = time.monotonic() + timeout_s
    context = Context()
    rclpy.init(args=[], context=context)
    harness = None
    try:
        harness = _Harness(context, namespace, params_file, params)
        harness.spin_until(harness.connected, timeout_s, 'the node to connect')
        left = list(harness.odom.config['left_wheel_joints'])
        right = list(harness.odom.config['right_wheel_joints'])
        names = left + right
        sent = 0
        n = len(samples)
        if reference is not None:
            _send_with_reference(harness, samples, reference, names, len(left), offset_ns,
                                 deadline, reference_frames, imu, positions)
            sent = n
        elif imu is not None:
            _send_with_imu(harness, samples, imu, names, len(left), offset_ns, deadline,
                           positions)
            sent = n
        while sent < n:
            stop = min(sent + WINDOW, n)
            for i in range(sent, stop):
                harness.publisher.publish(_joint_state(
                    names, len(left), int(samples.t_ns[i]) + offset_ns, samples.omega_l[i],
                    samples.omega_r[i], None if positions is None else positions[i]))
            sent = stop
            target = sent
            harness.spin_until(lambda: harness.odom.counters['received'] >= target,
                               max(deadline - time.monotonic(), 0.0),
                               f'the node to take sample {target} of {n}')
        harness.spin_until(
            lambda: len(harness.received) >= harness.odom.counters['published'],
            max(deadline - time.monotonic(), 0.0), 'the last odometry messages')
        return _result(harness.received, offset_ns, harness.odom.counters)
    finally:
        if harness is not None:
            harness.close()
        context.try_shutdown()
