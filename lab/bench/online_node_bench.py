"""Online calibration through the real node: process CPU per wheel sample, online on vs off.

Two real odometry nodes (``odom_node.main``, ``rclpy.spin``, each in its own process, pinned to
the same core when the machine has two or more), one with ``online.enabled`` and one without,
run the same parameters file (``edd_asymmetric`` with a calibrated noise). A driver in this
process (the :class:`lab.bench.node_bench.Driver`, pinned to another core) publishes
JointState at 1 kHz, stamped with the wall clock, with constant wheel speeds (the left wheels
``LEFT`` rad/s, the right ``RIGHT``: a wide arc), and a nav_msgs/Odometry on
``reference/odom`` at 10 Hz: the exact pose of that arc under a ground ``SLIP`` slower than the
file says, so the learner cuts segments (a 2 m / 1 rad horizon: every few seconds) and learns.
The off node has no reference subscription (online off): it gets the same JointState.

The two nodes are driven in alternating blocks (off, on, on, off, ...) so a machine that drifts
moves both; the CPU time of each node's process (every thread, DDS included, from
``/proc/<pid>/task/*/schedstat``) over its blocks is divided by the JointState messages sent.
The ratio on/off is measured in this one run (never asserted). Run::

    python -m lab.bench.online_node_bench --seconds 60 --rounds 6
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from typing import Any

from lab.bench.node_bench import (cpu_ns, Driver, NS_PER_S, percentile, pin, pin_driver,
                                  SLEEP_ABOVE_NS, SLEEP_S, sut_command)
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.odometry.se2 import step_scalar
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig

LEFT, RIGHT = 4.0, 5.0          # rad/s: about 0.6 m/s on an arc of a few metres' radius
SLIP = 0.1                      # the reference's ground: 10 % slower than the file says
REFERENCE_HZ = 10.0
MODEL = 'edd_asymmetric'


def node_params(online: bool, augmented: str = '') -> dict[str, str]:
    """Return the node parameters (command-line strings) of one SUT.

    ``augmented``: '' (the plain model), 'named' or 'residual': the augmented models of
    ``lab.bench.online_bench`` (``AUGMENTED``, ``RESIDUAL``) on the same base parameters.
    """
    params = {'model': MODEL, f'models.{MODEL}.noise.calibrated': 'true',
              **{f'models.{MODEL}.{k}': repr(float(v)) for k, v in DEFAULT_TRUE_PARAMS.items()}}
    if augmented:
        from lab.bench.online_bench import AUGMENTED, RESIDUAL
        flat = RESIDUAL if augmented == 'residual' else AUGMENTED
        params.update({k: v if isinstance(v, str) else repr(float(v)) for k, v in flat.items()
                       if k == 'model' or k.startswith('augmented.')})
    if online:
        params['online.enabled'] = 'true'
    return params


def reference_twist() -> tuple[float, float, float]:
    """Return the body twist of the reference's ground at the driver's wheel speeds."""
    model = get_model(MODEL)
    geometry = SimConfig().geometry
    k = model.vector(DEFAULT_TRUE_PARAMS, geometry)
    vx, vy, w = (float(v) for v in model.twist(k, geometry, LEFT, RIGHT))
    return vx * (1.0 - SLIP), vy * (1.0 - SLIP), w * (1.0 - SLIP)


class OnlineDriver(Driver):
    """The node benchmark's driver, also publishing the reference (module docstring)."""

    def __init__(self, namespace: str, domain_id: int) -> None:
        super().__init__(namespace, domain_id)
        from nav_msgs.msg import Odometry
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rclpy.serialization import serialize_message
        from sensor_msgs.msg import JointState
        self.ref_pub = self.node.create_publisher(
            Odometry, 'reference/odom', QoSProfile(depth=10,
                                                   reliability=ReliabilityPolicy.RELIABLE))
        template = JointState()
        template.name = ['front_left_wheel_joint', 'rear_left_wheel_joint',
                         'front_right_wheel_joint', 'rear_right_wheel_joint']
        template.velocity = [LEFT, LEFT, RIGHT, RIGHT]
        self._buffer = bytearray(serialize_message(template))
        self._odometry = Odometry
        from diagnostic_msgs.msg import DiagnosticArray
        self.diag_sub = self.node.create_subscription(
            DiagnosticArray, '/diagnostics', lambda msg: None,
            QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self.twist = reference_twist()
        self.first_ns: int | None = None
        self.references = 0
        self.with_reference = True

    def online_status(self, namespace: str) -> dict[str, str]:
        """Return the last /diagnostics values of the node in ``namespace`` ({}: none came)."""
        last: dict[str, str] = {}
        handle = self.diag_sub.handle
        while True:
            with handle:
                item = handle.take_message(self.diag_sub.msg_type, False)
            if item is None:
                return last
            for status in item[0].status:
                values = {kv.key: kv.value for kv in status.values}
                if status.name.startswith(namespace + '/'):
                    last = values

    def publish(self) -> int:
        stamp_ns = super().publish()
        if self.first_ns is None:
            self.first_ns = stamp_ns
        return stamp_ns

    def publish_reference(self) -> None:
        """Publish the reference pose of the arc at the wall clock now."""
        if self.first_ns is None or not self.with_reference:
            return
        stamp_ns = time.time_ns()
        x, y, yaw, _, _ = step_scalar(0.0, 0.0, 0.0, *self.twist,
                                      (stamp_ns - self.first_ns) * 1e-9)
        msg = self._odometry()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, NS_PER_S)
        msg.header.frame_id = 'reference'
        msg.child_frame_id = 'base_link'
        msg.pose.pose.position.x = float(x)
        msg.pose.pose.position.y = float(y)
        msg.pose.pose.orientation.z = math.sin(0.5 * yaw)
        msg.pose.pose.orientation.w = math.cos(0.5 * yaw)
        self.ref_pub.publish(msg)
        self.references += 1

    def paced(self, rate_hz: float, duration_s: float) -> tuple[list[int], float]:
        """Publish JointState at rate_hz and the reference at REFERENCE_HZ for duration_s."""
        period_ns = NS_PER_S / rate_hz
        ref_period_ns = NS_PER_S / REFERENCE_HZ
        sent: list[int] = []
        start_ns = time.monotonic_ns()
        end_ns = start_ns + int(duration_s * NS_PER_S)
        next_ns = float(start_ns)
        next_ref_ns = float(start_ns)
        while True:
            now_ns = time.monotonic_ns()
            if now_ns >= end_ns:
                break
            if now_ns >= next_ns:
                sent.append(self.publish())
                next_ns += period_ns
                if now_ns >= next_ref_ns:
                    self.publish_reference()
                    next_ref_ns += ref_period_ns
                continue
            if not self.take_all() and next_ns - now_ns > SLEEP_ABOVE_NS:
                time.sleep(SLEEP_S)
        elapsed_s = (time.monotonic_ns() - start_ns) / NS_PER_S
        return sent, len(sent) / elapsed_s


class OnlineSut:
    """One node process and its driver (as node_bench.Sut, with the reference driver)."""

    def __init__(self, label: str, online: bool, domain_id: int, cpu: int | None,
                 with_reference: bool = True, augmented: str = '') -> None:
        import subprocess
        self.label = label
        namespace = f'/online_bench_{os.getpid()}_{label.replace(",", "").replace(" ", "_")}'
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED='1')
        command = sut_command('odom', namespace, node_params(online, augmented))
        self.proc = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True)
        if cpu is not None:
            pin(self.proc.pid, cpu)
        self.namespace = namespace
        self.driver = OnlineDriver(namespace, domain_id)
        self.driver.with_reference = with_reference
        self.driver.wait_connected(30.0, self.proc)
        if online:   # the reference subscription matched too
            deadline = time.monotonic() + 30.0
            while self.driver.ref_pub.get_subscription_count() == 0:
                if time.monotonic() > deadline:
                    raise RuntimeError('the online node did not subscribe to reference/odom')
                time.sleep(0.02)
        self.driver.paced(500.0, 0.5)
        self.driver.spin_for(0.2)
        self.cpu_ns = 0
        self.sent = 0
        self.received = 0
        self.latency_us: list[float] = []

    def block(self, rate_hz: float, seconds: float) -> None:
        """Drive the node for one block; add its CPU time and messages."""
        driver = self.driver
        driver.received.clear()
        before = cpu_ns(self.proc.pid)
        sent, _ = driver.paced(rate_hz, seconds)
        after = cpu_ns(self.proc.pid)
        driver.spin_for(0.2)
        self.cpu_ns += (after or 0) - (before or 0)
        self.sent += len(sent)
        got = [(driver.received[s] - s) / 1e3 for s in sent if s in driver.received]
        self.received += len(got)
        self.latency_us += got

    def row(self) -> dict[str, Any]:
        return {'label': self.label, 'sent': self.sent, 'received': self.received,
                'cpu_us_per_sample': self.cpu_ns / 1e3 / max(self.sent, 1),
                'cpu_us_per_output': self.cpu_ns / 1e3 / max(self.received, 1),
                'p50_latency_us': percentile(self.latency_us, 50),
                'references': self.driver.references}

    def close(self) -> str:
        self.status = self.driver.online_status(self.namespace)
        self.driver.close()
        self.proc.terminate()
        try:
            _, stderr = self.proc.communicate(timeout=10)
        except Exception:   # noqa: BLE001 (a bench cleans up whatever happened)
            self.proc.kill()
            _, stderr = self.proc.communicate()
        return (stderr or '').strip()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, default=60.0,
                        help='driving time per node, split into --rounds blocks')
    parser.add_argument('--rounds', type=int, default=6)
    parser.add_argument('--rate', type=float, default=1000.0, help='JointState rate (Hz)')
    parser.add_argument('--no-reference-node', action='store_true',
                        help='also run a third node, online on but sent no reference (splits '
                        'the subscription and per-sample cost from the learning)')
    parser.add_argument('--augmented', choices=('named', 'residual'), default='',
                        help="both nodes run an augmented model (online_bench's: named "
                        'extensions, or a residual model with a rate term)')
    args = parser.parse_args(argv)
    cpu = pin_driver(sorted(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity')
                     else [])
    domain = 40 + os.getpid() % 50
    more = {'augmented': args.augmented}
    suts = [OnlineSut('off', False, domain, cpu, **more),
            OnlineSut('on', True, domain, cpu, **more)]
    if args.no_reference_node:
        suts.append(OnlineSut('on, no reference', True, domain, cpu, with_reference=False,
                              **more))
    try:
        block_s = args.seconds / args.rounds
        for index in range(args.rounds):
            for sut in (suts if index % 2 == 0 else suts[::-1]):
                sut.block(args.rate, block_s)
        rows = [sut.row() for sut in suts]
    finally:
        logs = [sut.close() for sut in suts]
    off, on = rows[:2]
    for row in rows:
        print(f"online {row['label']}: {row['cpu_us_per_sample']:.1f} us CPU per wheel "
              f"sample sent, {row['cpu_us_per_output']:.1f} per Odometry back ({row['sent']} "
              f"JointState at {args.rate:g} Hz, {row['received']} Odometry back, "
              f"{row['references']} reference poses at {REFERENCE_HZ:g} Hz, "
              f"p50 latency {row['p50_latency_us']:.0f} us)")
    for row in rows[1:]:
        print(f'ratio {row["label"]} / off per wheel sample sent: '
              f'{row["cpu_us_per_sample"] / off["cpu_us_per_sample"]:.3f}; per Odometry back: '
              f'{row["cpu_us_per_output"] / off["cpu_us_per_output"]:.3f}')
    print('(process CPU time of each node, this run; a node that cannot keep up drops '
          'JointState: see the counts)')
    for sut in suts:
        print(f'node {sut.label} /diagnostics: ' + ', '.join(
            f'{key} {sut.status.get(key, "-")}' for key in (
                'count.integrated', 'online.state', 'count.online_segments',
                'count.reference_accepted', 'online.alpha_l', 'online.alpha_r')))
    if logs[1]:
        print('online node stderr (last lines):', *logs[1].splitlines()[-3:], sep='\n  ')
    return 0


if __name__ == '__main__':
    sys.exit(main())
