"""Wheel speeds from two std_msgs/Float64 topics, paired as the node pairs them."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from skidkin_ros.adapters.bags.common import FLOAT64, NS_PER_S
from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.core.odometry.wheels import pair_wheel_streams
from skidkin_ros.errors import RecordingError


class FloatPairMixin:
    """Detection and pairing of a left and a right Float64 topic."""

    def _detect_float_pair(self) -> tuple[str, str] | None:
        floats = [t for t, m in self.topics().items() if m == FLOAT64]
        left = [t for t in floats if 'left' in t.lower()]
        right = [t for t in floats if 'right' in t.lower()]
        if len(left) == 1 and len(right) == 1:
            self.notes.append(f'wheel speeds: no JointState topic; using Float64 topics '
                              f'{left[0]} (left) and {right[0]} (right)')
            return left[0], right[0]
        return None

    def _read_float_pair(self, left_topic: str | None, right_topic: str | None,
                         max_speed: float, pair_tolerance_s: float) -> WheelSamples:
        """Pair two std_msgs/Float64 wheel topics on bag receive time, as odom_node pairs them.

        The messages of both topics are taken in recording order and paired by the node's own
        rule (:class:`~skidkin_ros.core.odometry.wheels.WheelPairer`): a left and a right value
        received within ``pair_tolerance_s`` form one sample stamped with the later receive
        time; a value whose partner does not come in time is dropped. A pair with a non-finite
        or implausible value is dropped, as the node's integrator rejects it; of pairs with the
        same stamp the last is kept (the node holds its speeds).
        """
        if left_topic is None or right_topic is None:
            raise RecordingError('wheel speeds from Float64 topics need both a left and a right '
                                 f'topic. Topics present: {self._listing()}')
        if left_topic == right_topic:
            raise RecordingError(f'wheel speeds: the left and right Float64 topics are both '
                                 f'{left_topic}; name one topic per side')
        self.select(FLOAT64, left_topic, 'left wheel speed')
        self.select(FLOAT64, right_topic, 'right wheel speed')
        sides = {left_topic: 'left', right_topic: 'right'}
        events = ((sides[topic], t_ns, float(msg.data))
                  for topic, t_ns, msg in self.messages_of([left_topic, right_topic]))
        pairs, unpaired = pair_wheel_streams(events, pair_tolerance_s * NS_PER_S)
        t_ns: list[int] = []
        omega_l: list[float] = []
        omega_r: list[float] = []
        for t, wl, wr in pairs:
            if not self._plausible_pair(((left_topic, wl), (right_topic, wr)), max_speed):
                continue
            if t_ns and t <= t_ns[-1]:
                if t < t_ns[-1]:  # storage files out of order: the node rejects it as older
                    self._drop(left_topic, 'stamp out of order')
                    continue
                omega_l[-1], omega_r[-1] = wl, wr
                continue
            t_ns.append(t)
            omega_l.append(wl)
            omega_r.append(wr)
        if not t_ns:
            raise RecordingError(
                f'wheel speeds: no valid left/right pair on {left_topic} and {right_topic} '
                f'within pair_tolerance {pair_tolerance_s:g} s ({unpaired} unpaired; '
                f'{self._reasons(left_topic)}; {self._reasons(right_topic)})')
        for topic in (left_topic, right_topic):
            self._note_drops(topic, len(t_ns))
        self.notes.append(f'wheel speeds: {left_topic} and {right_topic} paired on bag receive '
                          f'time within pair_tolerance {pair_tolerance_s:g} s, as odom_node '
                          f'pairs them ({len(t_ns)} samples, {unpaired} value(s) without a '
                          'partner dropped)')
        self.wheel_input = {'input': 'wheel_topics', 'left_topic': left_topic,
                            'right_topic': right_topic}
        return WheelSamples(np.array(t_ns, dtype=np.int64), omega_l, omega_r)

    def _plausible_pair(self, values: Sequence[tuple[str, float]], max_speed: float) -> bool:
        """Tell whether both speeds are finite and within max_speed; count the faulty side."""
        good = True
        for topic, value in values:
            if not math.isfinite(value):
                self._drop(topic, 'non-finite speed')
                good = False
            elif abs(value) > max_speed:
                self._drop(topic, f'speed beyond {max_speed:g} rad/s')
                good = False
        return good
