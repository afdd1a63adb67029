"""Node benchmark: JointState in, Odometry out, latency and sustained rate versus a bare relay.

Process layout (identical for every system under test, SUT):

* the SUT runs alone in a subprocess, pinned to one core when the machine has two or more:
  either the real odometry node (``odom_node.main``: ``rclpy.spin`` on a SingleThreadedExecutor)
  or a bare relay with the same structure (``rclpy.spin``, the same input QoS -- sensor data,
  best effort, depth 5 -- and the same output QoS -- reliable, depth 10) whose callback copies
  the stamp into an Odometry and publishes it, with no computation (the issue's yardstick:
  rclpy's standard path, which deserializes the JointState and serializes the Odometry);
* a second reference, the serialized relay: the same relay subscribed raw, publishing a
  pre-serialized Odometry with the stamp bytes patched in. It converts no message at all, which
  is rclpy's floor; the node too reads and writes serialized messages (skidkin_ros.node.wire),
  so the node against this relay is what the odometry itself costs;
* the driver runs in the calling process (pinned to another core): it publishes JointState at a
  paced rate with ``header.stamp`` = the wall clock just before ``publish`` and takes the
  Odometry back; latency = wall clock at receipt - stamp (the same host clock on both sides).

The relay and a node run side by side (both pinned to the same core, one driven at a time):
:func:`paired_steps` alternates them in short blocks, so a machine that drifts moves both and
the ratio of paired p50s stays put (on a shared virtual machine, the p50 of the same relay at
1 kHz swings between 0.35 and 2.5 ms from one half-second to the next).

Per rate step: p50/p99 latency, messages sent/received (drops = sent - received: the SUT input
is best effort, so a SUT that cannot keep up loses messages) and the SUT's CPU time over the
step (sum of ``/proc/<pid>/task/*/schedstat``, every thread incl. DDS), divided by the messages.
The ladder climbs until the first step that loses more than 0.1 % of its messages (a
saturated SUT loses hundreds; one scheduler hiccup of a few ms on a shared machine loses a
few, since the input queue holds 5) or that the driver cannot pace.

Start one SUT by hand: ``python lab/bench/node_bench.py sut odom -- --ros-args -p model:=roc``.
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
from pathlib import Path
import struct
import subprocess
import sys
import time
from typing import Any, Mapping, Sequence

NS_PER_S = 1_000_000_000
JOINTS = ('front_left_wheel_joint', 'rear_left_wheel_joint', 'front_right_wheel_joint',
          'rear_right_wheel_joint')
OUTPUT_DEPTH = 10
CDR_STAMP = struct.Struct('<iI')  # header.stamp right after the 4-byte CDR header
SLEEP_ABOVE_NS = 400_000  # sleep between sends only when the next one is this far off
SLEEP_S = 0.0001
DROP_TOLERANCE = 0.001  # a held step loses at most this fraction (scheduler hiccups)
_instance = itertools.count()
SUT_KINDS = ('relay', 'relay_serialized', 'odom')
SERIALIZED_RELAY_LABEL = 'serialized rclpy relay (no message conversion)'


# The node configurations measured besides the five models at their defaults (node parameters as
# command-line strings). Shared by lab/bench/run.py and lab/bench/callback_bench.py.
CALIBRATED_CASE = ('edd_symmetric, calibrated covariance',
                   {'model': 'edd_symmetric', 'models.edd_symmetric.noise.calibrated': 'true'})
AUGMENTED_VALUES = {
    # time_offset stays 0: it shifts the output stamps, which the driver matches replies by.
    'augmented.first_order_lag.tau_s': '0.08',
    'augmented.speed_slip.k': '0.05', 'augmented.direction_asymmetry.k': '0.1',
    'augmented.lateral_skid.k': '0.03', 'augmented.icr_offset.x_m': '0.05',
    'augmented.ratio_yaw_slip.k': '0.2', 'augmented.terrain_regime.k': '0.1',
    'augmented.terrain_regime.switch_s': '30.0', 'augmented.acceleration_slip.tau_s': '0.1',
}


def augmented_params() -> tuple[str, dict[str, str]]:
    """Return the label and node parameters of the heaviest augmented model."""
    from skidkin_ros.core.kinematics.augmented import AUGMENTED_NAME
    from skidkin_ros.core.kinematics.extensions import EXTENSIONS
    # One extension of each group (a model holds one lag: the whole-twist one, the costliest).
    extensions, groups = [], set()
    for name, ext in EXTENSIONS.items():
        if name != 'sparse_correction' and not (ext.group and ext.group in groups):
            extensions.append(name)
            groups.add(ext.group)
    label = f'{AUGMENTED_NAME}: edd_symmetric + {len(extensions)} extensions'
    params = {'model': AUGMENTED_NAME, 'augmented.base': 'edd_symmetric',
              'augmented.extensions': ','.join(extensions)}
    # Non-zero values, of the size the effects study finds, so no term is a no-op.
    params.update({name: value for name, value in AUGMENTED_VALUES.items()
                   if name.split('.')[1] in extensions})
    return label, params


# ---------------------------------------------------------------------------------- the SUTs
def run_relay(argv: Sequence[str], serialized: bool = False) -> int:
    """Spin the bare relay: JointState -> Odometry with the stamp copied, nothing computed.

    serialized: take the JointState serialized and publish a pre-serialized Odometry with the
    stamp bytes patched in (rclpy's floor: no message conversion at all, as the node does).
    """
    from nav_msgs.msg import Odometry
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    class Relay(Node):
        """Subscribe JointState, publish an Odometry carrying its stamp."""

        def __init__(self) -> None:
            super().__init__('relay')
            qos = QoSProfile(depth=OUTPUT_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
            self.pub = self.create_publisher(Odometry, 'odom', qos)
            template = Odometry()
            template.header.frame_id = 'odom'
            template.child_frame_id = 'base_link'
            self.buffer = bytearray(serialize_message(template))
            self.create_subscription(
                JointState, 'joint_states',
                self.on_serialized if serialized else self.on_joint_state,
                qos_profile_sensor_data, raw=serialized)

        def on_joint_state(self, msg: JointState) -> None:
            out = Odometry()
            out.header.stamp = msg.header.stamp
            out.header.frame_id = 'odom'
            out.child_frame_id = 'base_link'
            self.pub.publish(out)

        def on_serialized(self, data: bytes) -> None:
            # header.stamp opens both messages (the driver sends little-endian CDR).
            self.buffer[4:12] = data[4:12]
            self.pub.publish(bytes(self.buffer))

    rclpy.init(args=list(argv))
    node = None
    try:
        node = Relay()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def run_odom(argv: Sequence[str]) -> int:
    """Spin the real odometry node exactly as ``ros2 run`` would."""
    from skidkin_ros.node.odom_node import main
    return main(list(argv))


def sut_command(kind: str, namespace: str, params: Mapping[str, str] | None = None
                ) -> list[str]:
    """Return the command line that starts one SUT in a fresh interpreter.

    params: node parameters as ROS command-line values (e.g. ``{'model': 'roc'}``).
    """
    ros_args = ['--ros-args', '-r', f'__ns:={namespace}', '--log-level', 'warn']
    for name, value in (params or {}).items():
        ros_args += ['-p', f'{name}:={value}']
    return [sys.executable, str(Path(__file__).resolve()), 'sut', kind, '--', *ros_args]


# ---------------------------------------------------------------------------------- measuring
def cpu_ns(pid: int) -> int | None:
    """Return the CPU time (ns) of every thread of a process, None when /proc cannot tell."""
    total = 0
    try:
        tasks = os.listdir(f'/proc/{pid}/task')
    except OSError:
        return None
    for task in tasks:
        try:
            with open(f'/proc/{pid}/task/{task}/schedstat', encoding='ascii') as stream:
                total += int(stream.read().split()[0])
        except (OSError, ValueError, IndexError):
            continue  # a thread that ended between listdir and open
    return total


def percentile(values: Sequence[float], q: float) -> float:
    """Return the q-th percentile of the values, q in 0-100 (interpolated; NaN if empty)."""
    if not values:
        return math.nan
    ordered = sorted(values)
    pos = (len(ordered) - 1) * q / 100.0
    lo = int(math.floor(pos))
    hi = min(lo + 1, len(ordered) - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (pos - lo)


def pin(pid: int, cpu: int) -> None:
    """Pin a process to one CPU when the platform allows it (no-op elsewhere)."""
    if hasattr(os, 'sched_setaffinity') and cpu in os.sched_getaffinity(0):
        try:
            os.sched_setaffinity(pid, {cpu})
        except OSError:
            pass


class Driver:
    """Publisher of JointState and collector of Odometry, in a private rclpy context.

    The driver must cost far less than any SUT, or it would be the bottleneck: it publishes a
    pre-serialized JointState with only the stamp patched, takes the replies serialized (no
    executor, no deserialization; the stamp is read from the CDR bytes) and times each reply
    with the middleware's receive timestamp, so when the driver polls does not matter.
    """

    def __init__(self, namespace: str, domain_id: int) -> None:
        from nav_msgs.msg import Odometry
        import rclpy
        from rclpy.context import Context
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rclpy.serialization import serialize_message
        from sensor_msgs.msg import JointState

        self.context = Context()
        rclpy.init(args=[], context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node('bench_driver', namespace=namespace, context=self.context,
                                      use_global_arguments=False, enable_rosout=False,
                                      start_parameter_services=False)
        # The publisher is reliable like joint_state_broadcaster's; against the SUT's
        # best-effort subscription the connection is best effort (drops are possible).
        self.pub = self.node.create_publisher(
            JointState, 'joint_states', QoSProfile(depth=10,
                                                   reliability=ReliabilityPolicy.RELIABLE))
        self.sub = self.node.create_subscription(
            Odometry, 'odom', lambda msg: None,
            QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE), raw=True)
        template = JointState()
        template.name = list(JOINTS)
        template.velocity = [1.0, 1.0, 1.1, 1.1]
        self._buffer = bytearray(serialize_message(template))
        if self._buffer[:2] != b'\x00\x01':
            raise RuntimeError('expected little-endian CDR from the middleware')
        self.received: dict[int, int] = {}  # stamp ns -> receive ns (system clock)
        self._last_stamp_ns = 0

    def connected(self) -> bool:
        """Tell whether the SUT's subscription and publisher have both matched ours."""
        return self.pub.get_subscription_count() > 0 and self.sub.get_publisher_count() > 0

    def take_all(self) -> int:
        """Take every reply waiting; return how many were taken."""
        taken = 0
        handle = self.sub.handle
        while True:
            with handle:
                item = handle.take_message(self.sub.msg_type, True)
            if item is None:
                return taken
            data, info = item
            sec, nanosec = CDR_STAMP.unpack_from(data, 4)
            received_ns = int(info.get('received_timestamp') or 0) or time.time_ns()
            self.received[sec * NS_PER_S + nanosec] = received_ns
            taken += 1

    def spin_for(self, seconds: float) -> None:
        """Keep taking replies for a while (collects late ones)."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            if not self.take_all():
                time.sleep(0.001)

    def wait_connected(self, timeout_s: float, proc: subprocess.Popen) -> None:
        """Wait until the SUT has matched, or raise RuntimeError."""
        deadline = time.monotonic() + timeout_s
        while not self.connected():
            if proc.poll() is not None:
                raise RuntimeError(f'the SUT exited with code {proc.returncode} before matching')
            if time.monotonic() > deadline:
                raise RuntimeError(f'the SUT did not match within {timeout_s:g} s')
            time.sleep(0.02)

    def publish(self) -> int:
        """Publish one JointState stamped with the system clock now; return the stamp (ns)."""
        stamp_ns = max(time.time_ns(), self._last_stamp_ns + 1)
        self._last_stamp_ns = stamp_ns
        CDR_STAMP.pack_into(self._buffer, 4, *divmod(stamp_ns, NS_PER_S))
        self.pub.publish(bytes(self._buffer))
        return stamp_ns

    def paced(self, rate_hz: float, duration_s: float) -> tuple[list[int], float]:
        """Publish at rate_hz for duration_s; return the stamps sent and the achieved rate."""
        period_ns = NS_PER_S / rate_hz
        sent: list[int] = []
        start_ns = time.monotonic_ns()
        end_ns = start_ns + int(duration_s * NS_PER_S)
        next_ns = float(start_ns)
        while True:
            now_ns = time.monotonic_ns()
            if now_ns >= end_ns:
                break
            if now_ns >= next_ns:
                sent.append(self.publish())
                next_ns += period_ns
                continue
            if not self.take_all() and next_ns - now_ns > SLEEP_ABOVE_NS:
                time.sleep(SLEEP_S)
        elapsed_s = (time.monotonic_ns() - start_ns) / NS_PER_S
        return sent, len(sent) / elapsed_s

    def close(self) -> None:
        """Destroy the driver and shut its context down."""
        self.node.destroy_node()
        self.context.try_shutdown()


def _step(driver: Driver, pid: int, rate_hz: float, duration_s: float,
          drain_s: float) -> dict[str, Any]:
    driver.received.clear()
    cpu_before = cpu_ns(pid)
    sent, achieved_hz = driver.paced(rate_hz, duration_s)
    cpu_after = cpu_ns(pid)
    driver.spin_for(drain_s)
    latencies_us = [(driver.received[s] - s) / 1e3 for s in sent if s in driver.received]
    n_sent, n_recv = len(sent), len(latencies_us)
    cpu_us = (None if cpu_before is None or cpu_after is None
              else (cpu_after - cpu_before) / 1e3)
    return {
        'rate_hz': rate_hz, 'achieved_hz': achieved_hz, 'sent': n_sent, 'received': n_recv,
        'dropped': n_sent - n_recv,
        'p50_latency_us': percentile(latencies_us, 50), 'p99_latency_us':
        percentile(latencies_us, 99), 'max_latency_us': max(latencies_us, default=math.nan),
        'cpu_us_per_msg': (cpu_us / n_sent if cpu_us is not None and n_sent else math.nan),
        'cpu_share': (cpu_us / 1e6 / duration_s if cpu_us is not None else math.nan),
    }


def held(step: dict[str, Any], pace_tolerance: float = 0.95) -> bool:
    """Tell whether a step ran at its rate and lost at most DROP_TOLERANCE of its messages."""
    return (step['dropped'] <= DROP_TOLERANCE * step['sent']
            and step['achieved_hz'] >= pace_tolerance * step['rate_hz'])


class Sut:
    """One system under test: its process (pinned to ``cpu``) and the driver that talks to it.

    kind: one of SUT_KINDS; label: the row name; params: node parameters (odom only). Raises
    RuntimeError (after cleaning up) when the SUT does not start and match.
    """

    def __init__(self, kind: str, label: str, params: Mapping[str, str] | None,
                 domain_id: int, cpu: int | None, warmup_s: float = 0.5,
                 drain_s: float = 0.2) -> None:
        self.kind = kind
        self.label = label
        self.params = dict(params or {})
        self.drain_s = drain_s
        namespace = f'/bench_{os.getpid()}_{next(_instance)}'
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED='1')
        self.proc = subprocess.Popen(sut_command(kind, namespace, params), env=env,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                     text=True)
        if cpu is not None:
            pin(self.proc.pid, cpu)
        try:
            self.driver = Driver(namespace, domain_id)
        except BaseException:
            self.proc.kill()
            self.proc.communicate()
            raise
        try:
            self.driver.wait_connected(30.0, self.proc)
            self.driver.paced(500.0, warmup_s)
            self.driver.spin_for(drain_s)
        except RuntimeError:
            self.close()
            raise

    def step(self, rate_hz: float, seconds: float, **tags: Any) -> dict[str, Any]:
        """Drive the SUT at rate_hz for seconds; return the step's row (with ``tags``)."""
        row = _step(self.driver, self.proc.pid, rate_hz, seconds, self.drain_s)
        row.update(tags)
        return row

    def ladder(self, rates: Sequence[float], seconds: float) -> list[dict[str, Any]]:
        """Climb the rates until one is not held; return every step tried."""
        rows = []
        for rate_hz in rates:
            rows.append(self.step(rate_hz, seconds, ladder=True))
            if not held(rows[-1]):
                break
        return rows

    def close(self) -> list[str]:
        """Stop the driver and the SUT; return the last lines of the SUT's stderr."""
        self.driver.close()
        self.proc.terminate()
        try:
            _, stderr = self.proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            _, stderr = self.proc.communicate()
        return (stderr or '').strip().splitlines()[-5:]


def paired_steps(reference: Sut, sut: Sut, plan: Sequence[tuple[float, float]],
                 rounds: int) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Alternate the reference and the SUT in short blocks at every rate of the plan.

    Each (rate, seconds) of the plan is split into ``rounds`` blocks per SUT, run as
    reference, SUT, SUT, reference, ... so both see the same machine at the same time: a
    machine that drifts (frequency, other load) moves both, and the ratio of the paired p50s
    stays put. Returns (the SUT's steps, the reference's steps), each tagged with its round.
    """
    sut_rows: list[dict[str, Any]] = []
    ref_rows: list[dict[str, Any]] = []
    for rate_hz, seconds in plan:
        block_s = seconds / rounds
        for index in range(rounds):
            order = ((reference, ref_rows), (sut, sut_rows))
            for who, rows in (order if index % 2 == 0 else order[::-1]):
                rows.append(who.step(rate_hz, block_s, round=index, pair=sut.label))
    return sut_rows, ref_rows


def pin_driver(cpus: Sequence[int]) -> int | None:
    """Pin this (driver) process to the first CPU; return the SUTs' CPU (None: no pinning)."""
    if len(cpus) < 2:
        return None
    pin(0, cpus[0])
    return cpus[-1]


def _main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(description='Start one system under test of the node '
                                     'benchmark (normally started by lab/bench/run.py).')
    sub = parser.add_subparsers(dest='command', required=True)
    sut = sub.add_parser('sut', help='spin a relay or the odometry node')
    sut.add_argument('kind', choices=SUT_KINDS)
    sut.add_argument('ros_args', nargs=argparse.REMAINDER,
                     help='arguments for rclpy after --, e.g. -- --ros-args -p model:=roc')
    args = parser.parse_args(argv)
    ros_args = args.ros_args[1:] if args.ros_args[:1] == ['--'] else args.ros_args
    if args.kind == 'odom':
        return run_odom(ros_args)
    return run_relay(ros_args, serialized=args.kind == 'relay_serialized')


if __name__ == '__main__':
    sys.exit(_main(sys.argv[1:]))
