"""In-process cost of the node's JointState callback, without DDS or the executor.

The latency benchmark (node_bench) measures the whole path; on one core at 1 kHz that path is
dominated by rclpy and the middleware, whose queueing swamps small differences. This script
isolates what differs between the two: it calls ``OdomNode._on_joint_state`` directly on a
stream of serialized JointStates (1 kHz stamps, four wheel joints; the node subscribes raw, so this
is what the executor hands it) and times it, next to what a bare relay costs per message
(rclpy deserializes the JointState, the callback builds an Odometry, copies the stamp and
publishes it). Nothing subscribes, so ``publish`` costs only the serialization.

Run: ``python lab/bench/callback_bench.py`` (prints a Markdown table; about 20 s).
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any, Sequence

import node_bench

NS_PER_S = node_bench.NS_PER_S
JOINTS = node_bench.JOINTS


def cases() -> list[tuple[str, dict[str, Any]]]:
    """Return (label, node parameters) of each configuration the latency benchmark runs."""
    from skidkin_ros.core.kinematics.models import MODEL_NAMES
    out = [(model, {'model': model}) for model in MODEL_NAMES]
    out.append(node_bench.CALIBRATED_CASE)
    out.append(node_bench.augmented_params())
    return [(label, {name: _typed(value) for name, value in params.items()})
            for label, params in out]


def _typed(value: str) -> Any:
    """Return a command-line parameter value as rclpy wants it (bool, float or str)."""
    if value in ('true', 'false'):
        return value == 'true'
    try:
        return float(value)
    except ValueError:
        return value


def _messages(n: int, start_ns: int) -> list[bytes]:
    """Return n serialized JointStates (what the node's raw subscription is handed)."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    out = []
    for i in range(n):
        msg = JointState()
        t_ns = start_ns + i * 1_000_000
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t_ns, NS_PER_S)
        msg.name = list(JOINTS)
        w = 2.0 + (i % 100) * 0.01
        msg.velocity = [w, w, 1.5 * w, 1.5 * w]
        out.append(serialize_message(msg))
    return out


def time_node(params: dict[str, Any], n: int, repeats: int) -> float:
    """Return the best mean µs per message of the node callback over ``repeats`` runs of n."""
    import rclpy.parameter
    from skidkin_ros.node.odom_node import OdomNode
    overrides = [rclpy.parameter.Parameter(k, value=v) for k, v in params.items()]
    node = OdomNode(parameter_overrides=overrides)
    try:
        best = float('inf')
        start_ns = node.get_clock().now().nanoseconds - 600 * NS_PER_S
        for _ in range(repeats):
            messages = _messages(n, start_ns)
            start_ns += (n + 10) * 1_000_000
            tic = time.perf_counter()
            for msg in messages:
                node._on_joint_state(msg)
            best = min(best, (time.perf_counter() - tic) / n * 1e6)
        if node.counters['published'] < repeats * (n - 1):
            raise RuntimeError(f'the node published {node.counters["published"]} of '
                               f'{repeats * n} samples: {dict(node.counters)}')
        return best
    finally:
        node.destroy_node()


def time_relay(n: int, repeats: int) -> float:
    """Return the best mean µs per message of a bare relay: deserialize, then its callback."""
    from nav_msgs.msg import Odometry
    import rclpy
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState
    node = rclpy.create_node('callback_bench_relay')
    pub = node.create_publisher(Odometry, 'relay_odom', 10)
    try:
        best = float('inf')
        for _ in range(repeats):
            messages = _messages(n, 0)
            tic = time.perf_counter()
            for data in messages:
                msg = deserialize_message(data, JointState)  # the executor's part for a relay
                out = Odometry()
                out.header.stamp = msg.header.stamp
                out.header.frame_id = 'odom'
                out.child_frame_id = 'base_link'
                pub.publish(out)
            best = min(best, (time.perf_counter() - tic) / n * 1e6)
        return best
    finally:
        node.destroy_node()


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--messages', type=int, default=3000, help='messages per run')
    parser.add_argument('--repeats', type=int, default=5, help='runs per case (best kept)')
    args = parser.parse_args(argv)
    import rclpy
    rclpy.init(args=['--ros-args', '--log-level', 'warn'])
    try:
        relay_us = time_relay(args.messages, args.repeats)
        print('| callback | µs per message (best of runs) | over the relay |')
        print('|---|---|---|')
        print(f'| bare relay (deserialize JointState, build Odometry, copy stamp, publish) '
              f'| {relay_us:.1f} | |')
        for label, params in cases():
            node_us = time_node(params, args.messages, args.repeats)
            print(f'| odom_node {label} | {node_us:.1f} | {node_us - relay_us:+.1f} µs |')
    finally:
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
