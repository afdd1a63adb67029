"""Wheel speeds from JointState (velocity, position or auto), with the node's rules."""

from __future__ import annotations

from collections import Counter
import math
from typing import Sequence

import numpy as np

from skidkin_ros.adapters.bags.common import (DEFAULT_MAX_DT_S, DEFAULT_MAX_WHEEL_ACCELERATION,
                                              DEFAULT_MAX_WHEEL_SPEED_RAD_S,
                                              DEFAULT_PAIR_TOLERANCE_S, JOINT_STATE, stamp_ns)
from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.core.odometry.controller import ControllerGeometry
from skidkin_ros.core.odometry.wheels import (check_position_count, check_velocity_count,
                                              drop_jumps, DuplicateJointError, joint_indices,
                                              MalformedMessageError, MissingJointError,
                                              positions_at, speeds_at, WheelSignal)
from skidkin_ros.core.timeunits import ns_to_s
from skidkin_ros.errors import RecordingError


class WheelsMixin:
    """read_wheels and the JointState reader."""

    # -- wheels ----------------------------------------------------------------------------------
    def read_wheels(self, topic: str | None = None, *,
                    left_joints: Sequence[str] | None = None,
                    right_joints: Sequence[str] | None = None,
                    left_topic: str | None = None, right_topic: str | None = None,
                    max_wheel_speed_rad_s: float = DEFAULT_MAX_WHEEL_SPEED_RAD_S,
                    pair_tolerance_s: float = DEFAULT_PAIR_TOLERANCE_S,
                    max_wheel_acceleration: float = DEFAULT_MAX_WHEEL_ACCELERATION,
                    max_dt_s: float = DEFAULT_MAX_DT_S,
                    wheel_signal: str = 'velocity', odometry_topic: str | None = None,
                    controller: ControllerGeometry | None = None) -> WheelSamples:
        """Return wheel speeds (rad/s) from a JointState topic, two Float64 topics or odometry.

        A drive controller's nav_msgs/Odometry (``odometry_topic``, or the only Odometry topic
        when ``controller`` is given and nothing else names the input): see
        :meth:`_read_odometry_wheels`; its ``controller`` geometry is required.

        JointState: stamps from header.stamp (a bag whose stamps are all zero uses receive
        time, noted); a side's speed is the mean of its joints' velocities, as the node takes it
        (:mod:`skidkin_ros.core.odometry.wheels`), or with ``wheel_signal`` position / auto the
        travel between joint positions, by the node's rule (:class:`WheelSignal`); joints default
        to those whose names contain 'left' / 'right'. Float64 pairs: see
        :meth:`_read_float_pair`. Either way, samples whose
        speed jumps faster than ``max_wheel_acceleration`` (rad/s^2) are dropped and noted
        (:meth:`_drop_jumps`).
        """
        if odometry_topic is not None or (controller is not None and topic is None
                                          and left_topic is None and right_topic is None):
            wheels = self._read_odometry_wheels(odometry_topic, controller,
                                                max_wheel_speed_rad_s)
        elif left_topic is not None or right_topic is not None:
            wheels = self._read_float_pair(left_topic, right_topic, max_wheel_speed_rad_s,
                                           pair_tolerance_s)
        else:
            pair = None
            if topic is None and JOINT_STATE not in self.topics().values():
                pair = self._detect_float_pair()
            if pair is not None:
                wheels = self._read_float_pair(*pair, max_wheel_speed_rad_s, pair_tolerance_s)
            else:
                if topic is None and JOINT_STATE not in self.topics().values():
                    self._no_wheel_input()
                chosen = self.select(JOINT_STATE, topic, 'wheel speeds')
                wheels = self._read_joint_states(chosen, left_joints, right_joints,
                                                 max_wheel_speed_rad_s, wheel_signal)
        return self._drop_jumps(wheels, max_wheel_acceleration, max_dt_s,
                                self.wheel_input.pop('by_position', None))

    def _drop_jumps(self, wheels: WheelSamples, max_acceleration: float,
                    max_dt_s: float, by_position: Sequence[bool] | None = None) -> WheelSamples:
        """Drop samples whose speed jumps, as the node rejects them; name the wheel at fault.

        Speeds measured by encoder positions (``by_position``) are exempt, as in the node.
        """
        keep, sides = drop_jumps(wheels.t_ns, wheels.omega_l, wheels.omega_r, max_acceleration,
                                 max_dt_s, by_position)
        dropped = len(keep) - sum(keep)
        if not dropped:
            return wheels
        source = self.wheel_input.get('topic') or ' and '.join(
            self.wheel_input.get(k, '') for k in ('left_topic', 'right_topic'))
        at_fault = ', '.join(f'{n} on the {side} wheel' for side, n in sides.items() if n)
        self.notes.append(
            f'wheel speeds: dropped {dropped} of {len(keep)} samples of {source} whose speed '
            f'jumped faster than max_wheel_acceleration {max_acceleration:g} rad/s^2 '
            f'({at_fault}): glitches of the wheel readings (the driver or the encoders are at '
            'fault, not the lidar); the node rejects them too')
        mask = np.array(keep, dtype=bool)
        return WheelSamples(wheels.t_ns[mask], np.asarray(wheels.omega_l)[mask],
                            np.asarray(wheels.omega_r)[mask])

    def _detect_joints(self, topic: str, names: Sequence[str]) -> tuple[list[str], list[str]]:
        left = [n for n in names if 'left' in n.lower() and 'right' not in n.lower()]
        right = [n for n in names if 'right' in n.lower() and 'left' not in n.lower()]
        if not left or not right:
            raise RecordingError(f'wheel speeds: cannot tell left from right wheel joints on '
                                 f'{topic} (joints: {list(names)}); name them (left_wheel_joints '
                                 '/ right_wheel_joints)')
        self.notes.append(f'wheel speeds: {topic} joints {left} taken as left, {right} as right '
                          '(names containing left/right)')
        return left, right

    def _read_joint_states(self, topic: str, left_joints: Sequence[str] | None,
                           right_joints: Sequence[str] | None, max_speed: float,
                           wheel_signal: str = 'velocity') -> WheelSamples:
        left = list(left_joints) if left_joints else None
        right = list(right_joints) if right_joints else None
        stamps: list[int] = []
        receive: list[int] = []
        omega_l: list[float] = []
        omega_r: list[float] = []
        positions: list[tuple[tuple[float, ...], tuple[float, ...]] | None] = []
        index_cache: tuple[list[str], tuple[int, ...], tuple[int, ...]] | None = None
        seen_names: set[str] = set()
        read = 0
        for t_ns, msg in self.messages(topic):
            read += 1
            names = list(msg.name)
            seen_names.update(names)
            if left is None or right is None:
                if not any('left' in n.lower() for n in names):
                    self._drop(topic, 'without wheel joints')
                    continue
                auto_left, auto_right = self._detect_joints(topic, names)
                left = left or auto_left
                right = right or auto_right
            if index_cache is None or index_cache[0] != names:
                try:
                    index_cache = (names, *joint_indices(names, left, right))
                except MissingJointError:
                    self._drop(topic, 'without wheel joints')
                    continue
                except DuplicateJointError:  # refused as the node refuses it
                    self._drop(topic, 'with a wheel joint listed twice')
                    continue
            velocity = msg.velocity
            position = None
            if wheel_signal != 'velocity':
                try:
                    if check_position_count(len(names), len(msg.position)):
                        position = positions_at(msg.position, index_cache[1], index_cache[2])
                except MalformedMessageError:
                    self._drop(topic, 'with a position count other than the names')
                    continue
            if position is not None and wheel_signal == 'position' and not len(velocity):
                wl = wr = math.nan  # positions alone are enough
            else:
                try:
                    check_velocity_count(len(names), len(velocity))
                except MalformedMessageError:
                    self._drop(topic, 'without velocities')
                    continue
                wl, wr = speeds_at(velocity, index_cache[1], index_cache[2])
                if wheel_signal == 'velocity' and not (math.isfinite(wl) and math.isfinite(wr)):
                    self._drop(topic, 'non-finite speed')
                    continue
                if abs(wl) > max_speed or abs(wr) > max_speed:
                    self._drop(topic, f'speed beyond {max_speed:g} rad/s')
                    continue
            stamps.append(stamp_ns(msg.header))
            receive.append(t_ns)
            omega_l.append(wl)
            omega_r.append(wr)
            positions.append(position)
        if not read:
            raise RecordingError(
                f'wheel speeds: no message on {topic} could be read, though the recording lists '
                f'{self._count(topic)}: its messages were removed or cannot be read. Record the '
                'topic again, or check the recording (`ros2 bag reindex` rewrites its metadata)')
        if not stamps:
            wanted = (left or []) + (right or []) or 'named *left* / *right*'
            if self.counts[(topic, 'without wheel joints')] or left is None:
                raise RecordingError(
                    f'wheel speeds: no message on {topic} holds the wheel joints {wanted}; '
                    f'joints seen: {sorted(seen_names)}. Name them (left_wheel_joints / '
                    'right_wheel_joints)')
            raise RecordingError(f'wheel speeds: every message on {topic} was rejected '
                                 f'({self._reasons(topic)}); check the recording')
        t = self._header_or_receive(topic, np.array(stamps, np.int64), np.array(receive, np.int64))
        keep = self._keep_in_order(topic, t)
        self.wheel_input = {'input': 'joint_state', 'topic': topic,
                            'left_wheel_joints': list(left), 'right_wheel_joints': list(right),
                            'wheel_signal': wheel_signal}
        wheels = WheelSamples(t[keep], np.array(omega_l)[keep], np.array(omega_r)[keep])
        if wheel_signal == 'velocity':
            return wheels
        kept = [positions[i] for i in np.flatnonzero(keep)]
        return self._signal_speeds(topic, wheels, kept, wheel_signal, max_speed)

    def _signal_speeds(self, topic: str, wheels: WheelSamples,
                       positions: Sequence[tuple[tuple[float, ...], tuple[float, ...]] | None],
                       wheel_signal: str, max_speed: float) -> WheelSamples:
        """Return the speeds the node integrates under ``wheel_signal`` (WheelSignal's rule)."""
        signal = WheelSignal(wheel_signal, max_speed)
        keep = np.zeros(len(wheels), dtype=bool)
        omega_l = np.asarray(wheels.omega_l, dtype=float).copy()
        omega_r = np.asarray(wheels.omega_r, dtype=float).copy()
        used: Counter[str] = Counter()
        by_position = np.zeros(len(wheels), dtype=bool)
        for i, t_ns in enumerate(wheels.t_ns.tolist()):
            taken = signal.take(t_ns, omega_l[i], omega_r[i], positions[i])
            by_position[i] = taken.by_position
            if taken.warning is not None:
                self.notes.append(f'wheel speeds: {topic} at {ns_to_s(t_ns):.3f} s: '
                                  f'{taken.warning[1]}')
            if taken.speeds is None:
                self._drop(topic, {'no_position': 'without positions',
                                   'non_finite': 'non-finite position',
                                   'position_range': 'position beyond float resolution',
                                   'implausible': 'position jump beyond max_wheel_speed'
                                   }[taken.cause])
                continue
            omega_l[i], omega_r[i] = taken.speeds
            keep[i] = math.isfinite(omega_l[i]) and math.isfinite(omega_r[i])
            used[signal.in_use] += 1
        self.notes.append(f'wheel speeds: {topic} read with wheel_signal {wheel_signal}: '
                          + ', '.join(f'{n} intervals from the joint {kind}s'
                                      for kind, n in sorted(used.items())))
        self.wheel_input['wheel_signal_used'] = dict(used)
        self.wheel_input['by_position'] = by_position[keep].tolist()
        return WheelSamples(wheels.t_ns[keep], omega_l[keep], omega_r[keep])
