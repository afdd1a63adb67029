"""Online calibration: the reference quality gates (steps 1 and 2 of the recipe).

A reference pose is judged on arrival (NaN, stamp, frame, rate), turned into the base frame's
pose in wheel time, and judged once the wheel steps cover it (gap, wheel gap, jump, stall);
a good one is accepted into the chain of reference poses that the segments are cut from. The
methods are those of :class:`~skidkin_ros.core.online.calibrator.OnlineCalibrator` (a mixin;
the recipe is in that module's docstring).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from skidkin_ros.core.odometry.reference import base_pose, ReferenceStatus
from skidkin_ros.core.timeunits import NS_PER_S

__all__ = ['ReferenceGates', 'JUMP_CONFIRM', 'MAX_REFERENCES']

# Jumps in a row that mean the reference relocalised (its chain restarts there).
JUMP_CONFIRM = 3
# Reference poses kept for the window (beyond: the oldest go).
MAX_REFERENCES = 4096


class _Ref:
    """One accepted reference pose, base frame, in wheel time, with the cumulative path.

    ``gyro``: the gyro's integrated yaw since the start of its ``epoch`` (a run of reference
    intervals the gyro covered without a break; NaN without a gyro).
    """

    __slots__ = ('t_ns', 'x', 'y', 'yaw', 'path_m', 'gyro', 'epoch')

    def __init__(self, t_ns: int, x: float, y: float, yaw: float, path_m: float,
                 gyro: float = math.nan, epoch: int = 0) -> None:
        self.t_ns, self.x, self.y, self.yaw, self.path_m = t_ns, x, y, yaw, path_m
        self.gyro, self.epoch = gyro, epoch


class ReferenceGates:
    """The reference poses of :class:`OnlineCalibrator`: judged, then accepted (a mixin).

    ``gyro_turn(t_a, t_b)``: the gyro's yaw (rad) over that wheel-time interval, None where it
    does not cover it; None (the attribute): no gyro, the reference is not judged by one.
    ``gyro_noise``: (white noise rad/sqrt(s), bias sigma rad/s) of that gyro.
    """

    gyro_turn: Callable[[int, int], float | None] | None = None
    gyro_noise: tuple[float, float] = (0.0, 0.0)
    _gyro_refused = 0
    _gyro_epoch = 0
    last_refusal = ''   # the cause of the last reference pose not used (/diagnostics)
    _frames_seen: tuple[str, str] | None = None   # frames of the last pose accepted on arrival
    gyro_refused_ns = -(1 << 62)   # wheel time of the last pose the gyro refused

    def reference(self, t_ns: int, x: float, y: float, yaw: float, frame_id: str = '',
                  child_frame_id: str = '', yaw_variance: float = math.nan
                  ) -> tuple[ReferenceStatus, bool]:
        """Take a reference pose of the reference frame, stamped t_ns (reference clock).

        ``yaw_variance``: its pose covariance's yaw entry (rad^2; NaN: none), read by the
        heading rule (heading.py). Returns (status on arrival, whether the parameters changed).
        A pose accepted on arrival may still be judged a gap, a jump or a stall once the wheels
        cover it (counted then).
        """
        status = self._arrival(t_ns, x, y, yaw, frame_id, child_frame_id)
        if status is not ReferenceStatus.ACCEPTED:
            why = status.value.removeprefix('reference_')
            if status is ReferenceStatus.FUTURE:
                why = (f'{(t_ns - self._offset_ns - self._last_t1) * 1e-9:.3f} s ahead of the '
                       'last wheel sample (its clock ahead, or no wheel data for that long)')
            self._count(status, f'reference pose {why} (stamp {t_ns * 1e-9:.3f} s): not used; '
                        'the odometry goes on with the parameters learned so far')
            return status, False
        if self._heading_refused(yaw_variance):   # counted there, logged once
            if not self.position_learning():
                return ReferenceStatus.NO_HEADING, False
            # the reference frame's position alone (position.py): its heading is not one
            item = (t_ns - self._offset_ns, x, y, math.nan)
        else:
            bx, by, byaw = base_pose(x, y, yaw, self.params)
            item = (t_ns - self._offset_ns, bx, by, byaw)
        self._last_arrival_ns = t_ns
        self._note_frames(frame_id, child_frame_id)
        before = self.version
        if self._last_t1 is not None and item[0] <= self._last_t1 and not self._pending:
            self._judge(*item)
        else:
            self._pending.append(item)
            if len(self._pending) > MAX_REFERENCES:
                self._count(ReferenceStatus.UNCOVERED, 'reference poses wait for wheel data '
                            'that does not come: the oldest is dropped')
                self._pending.popleft()
            self._due_ns = self._pending[0][0]
        return status, self.version != before

    def _arrival(self, t_ns: int, x: float, y: float, yaw: float, frame_id: str,
                 child_frame_id: str) -> ReferenceStatus:
        params = self.params
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(yaw)):
            return ReferenceStatus.NON_FINITE
        if t_ns <= 0:
            return ReferenceStatus.BAD_STAMP
        if not params.frames_match(frame_id, child_frame_id):
            return ReferenceStatus.FRAME
        if (self._last_t1 is not None and t_ns - self._offset_ns - self._last_t1
                > max(params.max_gap, 1.0) * NS_PER_S + abs(self._offset_ns)):
            # a stamp hours ahead of the wheels, accepted, would refuse every later pose
            return ReferenceStatus.FUTURE
        last = self._last_arrival_ns
        if last is not None:
            if t_ns <= last:
                return ReferenceStatus.OLDER
            if t_ns - last < self._min_period_ns:
                return ReferenceStatus.RATE_LIMITED
        if abs(x) > 1e9 or abs(y) > 1e9:
            return ReferenceStatus.NON_FINITE
        return ReferenceStatus.ACCEPTED

    def _note_frames(self, frame_id: str, child_frame_id: str) -> None:
        """Warn when the poses' frames change and no frame is configured (two publishers?)."""
        frames, seen = (frame_id, child_frame_id), self._frames_seen
        self._frames_seen = frames
        params = self.params
        if (seen is not None and frames != seen
                and not (params.reference_frame_id and params.reference_child_frame_id)):
            self._warn('reference_frames_mixed', f'reference poses in frame_id/child_frame_id '
                       f'{seen[0][:64]!r}/{seen[1][:64]!r} then {frames[0][:64]!r}/'
                       f'{frames[1][:64]!r} (two publishers on one topic?): the learner cannot '
                       'tell them apart; set online.reference_frame_id and '
                       'reference_child_frame_id to the frames to learn from')

    def _count(self, status: ReferenceStatus, message: str) -> None:
        self.counters[status.value] += 1
        self.last_refusal = status.value
        self._warn(status.value, message)

    def _wheel_motion(self, t_a: int, t_b: int) -> tuple[float, float] | None:
        """Return the wheel travel (m) and rotation (rad) over (t_a, t_b]; None: not covered."""
        return self._steps.motion(t_a, t_b)

    def _judge(self, t_ns: int, x: float, y: float, yaw: float) -> None:
        """Judge a reference pose the wheels now cover; use it if it is good."""
        if not self._t1 or t_ns <= self._steps.first_start():
            self._count(ReferenceStatus.UNCOVERED, 'reference pose before the first wheel '
                        'step kept: normal for the first pose after a start or a change of '
                        'online.*; if it goes on, time_offset is wrong or wheel data missing')
            return
        if self.no_heading and self.position_learning():   # positions alone (position.py)
            self._judge_position(t_ns, x, y)
            return
        if math.isnan(yaw):   # a position kept before the heading was measured again
            return
        if self._heading_flat(t_ns, x, y, yaw):   # a heading constant while the wheels turn
            return
        seen, self._last_seen = self._last_seen, (t_ns, x, y, yaw)
        if seen is not None and seen[1:] == (x, y, yaw):
            moved = self._wheel_motion(seen[0], t_ns)
            self._stall_m += 0.0 if moved is None else moved[0]
            if self._stall_m > self.params.stall:
                self._count(ReferenceStatus.STALL, f'reference frozen while the wheels '
                            f'travelled {self._stall_m:.2f} m: not used, segment dropped')
                self._seg_start = None
                return
        else:
            self._stall_m = 0.0
        last = self._refs[-1] if self._refs else None
        if last is None:
            self._start_chain(t_ns, x, y, yaw)
            return
        if t_ns - last.t_ns > self.params.max_gap * NS_PER_S:
            self._count(ReferenceStatus.GAP, f'reference gap of {(t_ns - last.t_ns) * 1e-9:.2f} '
                        f's (max_gap {self.params.max_gap:g} s): segment dropped, restarting')
            self._start_chain(t_ns, x, y, yaw)
            return
        motion = self._wheel_motion(last.t_ns, t_ns)
        if motion is None:
            self._count(ReferenceStatus.WHEEL_GAP, 'the wheel data has a gap since the last '
                        'reference pose: segment dropped, restarting')
            self._start_chain(t_ns, x, y, yaw)
            return
        yaw = last.yaw + _wrap(yaw - last.yaw)
        dist = float(np.hypot(x - last.x, y - last.y))
        wheel_dist, wheel_rot = motion
        params = self.params
        if params.disagrees(abs(dist - wheel_dist), wheel_dist, (yaw - last.yaw) - wheel_rot,
                            wheel_rot):
            self._jumps += 1
            self._count(ReferenceStatus.JUMP, f'reference moved {dist:.2f} m / '
                        f'{yaw - last.yaw:+.2f} rad where the wheels say {wheel_dist:.2f} m / '
                        f'{wheel_rot:+.2f} rad: refused')
            if self._jumps >= JUMP_CONFIRM:
                self._start_chain(t_ns, x, y, yaw)
            return
        self._jumps = 0
        ref = _Ref(t_ns, x, y, yaw, last.path_m + dist)
        if self.gyro_turn is not None and not self._gyro_agrees(last, ref):
            return
        self._accept(ref)

    def _gyro_agrees(self, last: _Ref, ref: _Ref) -> bool:
        """Judge the reference's heading change against the gyro's (sets ref.gyro, epoch).

        Over the interval from the last pose and over the segment so far, the reference's
        heading change and the gyro's integrated yaw may differ by ``gyro_sigmas`` standard
        deviations of their noise: the reference's heading noise at both ends (the sigma in
        use, :meth:`~skidkin_ros.core.online.refnoise.RefNoiseLearner.reference_sigmas`), the
        gyro's white noise (imu.arw) and bias uncertainty (imu.bias_sigma) over the time. A pose
        beyond is refused (counted reference_gyro) and the segment dropped: learning pauses
        while the reference turns where the gyro does not. JUMP_CONFIRM refusals in a row restart
        the chain there (a reference that relocalised its heading).
        """
        turn = self.gyro_turn(last.t_ns, ref.t_ns)
        if turn is not None and math.isnan(turn):
            # the gyro's buffer (a few seconds) does not cover the interval: poses farther
            # apart than that are learned from unjudged, and counted so
            self.counters['reference_gyro_unchecked'] += 1
            turn = None
        if turn is None or math.isnan(last.gyro):   # the gyro does not cover it: a new epoch
            self._gyro_epoch += 1
            ref.gyro, ref.epoch = 0.0, self._gyro_epoch
            return True
        ref.gyro, ref.epoch = last.gyro + turn, last.epoch
        arw, bias_sigma = self.gyro_noise
        sigmas = self.params.gyro_sigmas
        # the reference's heading noise as the segments weigh it: measured (refnoise.py) or
        # configured; the configured value alone refused a reference within its bounds
        ref_var = 2.0 * self.reference_sigmas()[1] ** 2
        start = self._seg_start
        for a in (last, start):
            if a is None or a.epoch != ref.epoch or math.isnan(a.gyro):
                continue
            t_s = (ref.t_ns - a.t_ns) * 1e-9
            diff = (ref.yaw - a.yaw) - (ref.gyro - a.gyro)
            limit = sigmas * math.sqrt(ref_var + arw * arw * t_s + (bias_sigma * t_s) ** 2)
            if abs(diff) > limit:
                self._gyro_refused += 1
                self.gyro_refused_ns = ref.t_ns
                self._seg_start = None
                self._count(ReferenceStatus.GYRO, f'reference heading changed {diff:+.3f} rad '
                            f'more than the gyro over {t_s:.2f} s (limit {limit:.3f} rad, '
                            f'{sigmas:g} sigma): refused, segment dropped; learning paused')
                if self._gyro_refused >= JUMP_CONFIRM:
                    self._start_chain(ref.t_ns, ref.x, ref.y, ref.yaw)
                return False
        self._gyro_refused = 0
        return True

    def _start_chain(self, t_ns: int, x: float, y: float, yaw: float) -> None:
        self._refs.clear()
        self._jumps = 0
        self._gyro_refused = 0
        self._gyro_epoch += 1
        ref = _Ref(t_ns, x, y, yaw, 0.0, 0.0, self._gyro_epoch)
        self._refs.append(ref)
        self._seg_start = ref
        self._seg_version = self.version
        self._last_accepted_wheel_ns = t_ns
        self.counters[ReferenceStatus.ACCEPTED.value] += 1

    def _accept(self, ref: _Ref) -> None:
        refs = self._refs
        refs.append(ref)
        self.counters[ReferenceStatus.ACCEPTED.value] += 1
        self.travel_m += ref.path_m - refs[-2].path_m
        self._last_accepted_wheel_ns = ref.t_ns
        if len(refs) > MAX_REFERENCES:
            refs.popleft()
        start = self._seg_start
        if start is None:
            self._seg_start = ref
            self._seg_version = self.version
        elif self.options.ends(start.path_m, ref.path_m, ref.yaw - start.yaw,
                               ref.t_ns - start.t_ns):
            self._learn(start, ref)
            self._seg_start = ref
            self._seg_version = self.version
        if len(self.grounds) > 1 and not (
                0.0 <= ref.path_m - self._recognised_m < 0.5 * self.params.switch_window):
            self._recognised_m = ref.path_m
            self._recognise(ref)
        # the window needs only the last switch_window metres
        window = self.params.switch_window
        while len(refs) > 2 and refs[1].path_m <= ref.path_m - window and (
                self._seg_start is None or refs[1].t_ns <= self._seg_start.t_ns):
            refs.popleft()


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi
