"""The one integrator shared by the live node and every offline tool.

Wheel speeds are constant between samples: over [t_i, t_{i+1}] the robot moves with the speeds
the sample-interval convention gives (:mod:`skidkin_ros.core.odometry.interval`: sample i+1's by
default, sample i's for ``starting``, their mean for ``midpoint``); the batch functions below take
those *held* speeds, slot i held over [t_i, t_{i+1}) (:func:`~skidkin_ros.core.odometry.interval.
held_wheels` makes them), the streaming integrator combines two samples itself. Over each
interval the body twist is constant and the pose is
advanced by the exact SE(2) exponential, with a series branch for small rotations that is
continuous with the closed form (the step and the batch rollouts live in
:mod:`~skidkin_ros.core.odometry.se2`). The batch rollout (vectorized over many segments, used for
fitting) and the streaming integrator (used by the node and ``skidkin predict``) perform the same
additions in the same order, so they agree to the last bit.

Stateful sources (an augmented model with a first-order response, a time-in-drive regime; see
:mod:`skidkin_ros.core.kinematics.augmented`) carry a small state from sample to sample. Their
protocol is
:class:`StatefulTwistSource`: ``begin`` takes a new sample (returns the twist now published),
``advance`` gives the mean twist over the held interval and the state at its end. The streaming
integrator calls these two; the batch form :func:`stream_twists` runs the same recursion over whole
drives at once (``source.intervals``), and :func:`rollout_stream` integrates it like the
streaming integrator does, so offline fitting and the live node run one pipeline.
"""

from __future__ import annotations

from dataclasses import dataclass
import enum
import math
from typing import Any, Callable, Protocol

import numpy as np

from skidkin_ros.core.odometry.interval import (check_interval, DEFAULT_INTERVAL, held_speeds,
                                                interval_speed)
from skidkin_ros.core.odometry.se2 import (body_increment, compose, rollout, rollout_columns,
                                           rollout_segments, SMALL_ANGLE_RAD, step_scalar,
                                           wrap_angle)
from skidkin_ros.core.odometry.wheels import jump_limit, jumped_sides
from skidkin_ros.core.timeunits import ns_to_s

# The SE(2) step and the batch rollouts live in se2; re-exported here.
__all__ = [
    'SMALL_ANGLE_RAD',
    'body_increment',
    'compose',
    'step_scalar',
    'rollout',
    'rollout_segments',
    'rollout_columns',
    'wrap_angle',
    'TwistSource',
    'StatefulTwistSource',
    'is_stateful',
    'stream_twists',
    'rollout_stream',
    'SampleStatus',
    'StepResult',
    'IntegratorLimits',
    'StreamingIntegrator',
]


class TwistSource(Protocol):
    """What the streaming integrator runs: a bound model (or an augmented one)."""

    def twist(self, omega_l, omega_r) -> np.ndarray:
        ...


class StatefulTwistSource(Protocol):
    """A twist source with memory (``stateful = True``); the state is an immutable value.

    ``begin(state, t_ns, omega_l, omega_r, restart)`` takes a new sample (state None: the first
    sample; restart: after a gap, the dynamics restart) and returns (state, twist published now);
    ``advance(state, dt_s)`` returns (state at the end of the held interval, mean twist over it);
    ``published(state)`` the body twist at the end of an advanced interval (what the streaming
    integrator publishes after integrating it under ``ending`` or ``midpoint``);
    ``intervals(t_ns, omega_l, omega_r, dt_s, restart)`` is the batch form over (D, L) arrays and
    returns (published twists, mean twists), both (D, L, 3); ``output_offset_ns`` is added to the
    stamps of what is published (the true motion lags the wheel stamps by it).
    """

    stateful: bool
    output_offset_ns: int

    def twist(self, omega_l, omega_r) -> np.ndarray:
        ...

    def begin(self, state: Any, t_ns: int, omega_l: float, omega_r: float,
              restart: bool) -> tuple[Any, np.ndarray]:
        ...

    def advance(self, state: Any, dt_s: float) -> tuple[Any, np.ndarray]:
        ...

    def published(self, state: Any) -> tuple[float, float, float]:
        ...

    def intervals(self, t_ns: np.ndarray, omega_l: np.ndarray, omega_r: np.ndarray,
                  dt_s: np.ndarray, restart: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ...


def _scalar_twist(source: TwistSource, omega_l: float, omega_r: float
                  ) -> tuple[float, float, float]:
    """Return the twist of one sample as floats, by the source's scalar path when it has one."""
    scalar = getattr(source, 'scalar_twist', None)
    if scalar is not None:
        return scalar(omega_l, omega_r)
    vx, vy, w = np.asarray(source.twist(omega_l, omega_r), dtype=float).tolist()
    return vx, vy, w


def is_stateful(source: Any) -> bool:
    """Tell whether a twist source carries state between samples."""
    return bool(getattr(source, 'stateful', False))


def _as_rows(values, dtype=float) -> np.ndarray:
    array = np.asarray(values, dtype=dtype)
    return array[None] if array.ndim == 1 else array


def stream_twists(source: TwistSource, t_ns, omega_l, omega_r,
                  max_dt_s: float = math.inf, interval: str = DEFAULT_INTERVAL
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batch form of the streaming pipeline over clean drives (D, L) or one drive (L,).

    ``omega_l``/``omega_r`` are the samples as measured; ``interval`` the convention.
    Returns (twists of the speeds held over each interval (D, L, 3), mean twists over
    [t_i, t_i+1) (D, L, 3), step durations (D, L) with the last step and steps longer than
    ``max_dt_s`` set to 0, as the streaming integrator does not integrate across gaps). Padding:
    repeat the last stamp.
    """
    check_interval(interval)
    t = _as_rows(t_ns, np.int64)
    wl = held_speeds(_as_rows(omega_l), interval)
    wr = held_speeds(_as_rows(omega_r), interval)
    dt_s = np.zeros(t.shape)
    dt_s[:, :-1] = np.diff(t, axis=1) * 1e-9
    restart = np.zeros(t.shape, dtype=bool)
    restart[:, 1:] = dt_s[:, :-1] > max_dt_s
    dt_s[dt_s > max_dt_s] = 0.0
    if is_stateful(source):
        held, mean = source.intervals(t, wl, wr, dt_s, restart)
    else:
        held = np.asarray(source.twist(wl, wr), dtype=float)
        mean = held
    return held, mean, dt_s


def rollout_stream(source: TwistSource, t_ns, omega_l, omega_r, start=(0.0, 0.0, 0.0),
                   max_dt_s: float = math.inf, interval: str = DEFAULT_INTERVAL) -> np.ndarray:
    """Pose after every sample of one clean drive (L, 3), as the streaming integrator gives it."""
    _, mean, dt_s = stream_twists(source, t_ns, omega_l, omega_r, max_dt_s, interval)
    poses = rollout_segments(mean[:, :-1], dt_s[:, :-1], np.asarray(start, float)[None])
    return poses[0]


class SampleStatus(enum.Enum):
    """What the integrator did with a wheel sample."""

    INTEGRATED = 'integrated'        # the held speeds were integrated up to this sample
    FIRST = 'first'                  # first sample (or first after a reset/gap): held only
    DUPLICATE_STAMP = 'duplicate'    # dt = 0: speeds updated, nothing integrated
    OLDER_STAMP = 'older'            # older than the previous one: rejected
    GAP = 'gap'                      # dt > max_dt: not integrated across, restarted here
    NON_FINITE_SPEED = 'non_finite'  # NaN or inf wheel speed: rejected
    IMPLAUSIBLE_SPEED = 'implausible'  # |speed| > max_wheel_speed: rejected
    WHEEL_JUMP = 'wheel_jump'        # speed changed faster than max_wheel_acceleration: rejected
    NON_FINITE_STATE = 'non_finite_state'  # integration produced NaN/inf: rolled back

    @property
    def accepted(self) -> bool:
        return self in (SampleStatus.INTEGRATED, SampleStatus.FIRST,
                        SampleStatus.DUPLICATE_STAMP, SampleStatus.GAP)


@dataclass(frozen=True)
class IntegratorLimits:
    """Plausibility limits: max_dt_s bounds the integration step, the others the input.

    ``max_wheel_acceleration_rad_s2`` (inf: no check) rejects speeds that jump (see
    :mod:`skidkin_ros.core.odometry.wheels`).
    """

    max_dt_s: float = 0.5
    max_wheel_speed_rad_s: float = 100.0
    max_wheel_acceleration_rad_s2: float = math.inf


Triple = tuple[float, float, float]


@dataclass
class StepResult:
    """What one sample did. Poses and twists are plain float triples (the node's hot path).

    ``pose``: (x, y, yaw) after this sample, yaw unwrapped; ``twist``: the body twist now held
    (from this sample's speeds, what is published; a stateful source under ``ending`` or
    ``midpoint``: the one the pose integrated at the end of the interval, see
    :class:`StreamingIntegrator`); ``start_pose`` and ``step_twist``: where the
    integrated step started and the twist integrated over it (for a stateful source, its mean
    over the interval), equal to ``pose`` and ``twist`` when nothing was integrated.
    """

    status: SampleStatus
    pose: Triple
    twist: Triple
    dt_s: float = 0.0
    detail: str = ''
    start_pose: Triple | None = None
    step_twist: Triple | None = None
    step_wheels: tuple[float, float] | None = None  # the wheel speeds the step integrated


class StreamingIntegrator:
    """Sample-by-sample form of :func:`rollout`, with the plausibility checks of the node.

    ``step(t_ns, omega_l, omega_r)`` integrates from the previous stamp to ``t_ns`` with the
    speeds the sample-interval convention ``interval`` gives (the new sample's for ``ending``,
    the previous one's for ``starting``, their mean for ``midpoint``) and then holds the new
    speeds (the published twist is theirs). Stamps are integer nanoseconds. The state is kept in
    plain floats: numpy on three numbers costs more than the arithmetic, and this runs once per
    wheel sample in the node.

    A stateful source under ``ending`` or ``midpoint`` takes each interval's speeds when the
    sample that ends it arrives (``begin`` at the interval's start stamp, then ``advance``), as
    the batch form does with the held speeds; between samples its state is the one at the last
    stamp, and the published twist is the one the pose integrated at the end of that interval
    (``published``: the rate terms and the lag included; without a lag, the step's twist, so
    twist x dt is the pose increment). Only a first sample, a restart after a gap or a repeated
    stamp (nothing integrated) publishes what ``begin`` gives for the newest sample, at rate 0.
    """

    def __init__(self, source: TwistSource, limits: IntegratorLimits | None = None,
                 interval: str = DEFAULT_INTERVAL) -> None:
        self._source = source
        self.limits = limits or IntegratorLimits()
        self.interval = check_interval(interval)
        self._stateful = is_stateful(source)
        self._deferred = self._stateful and self.interval != 'starting'
        self._restart = False
        self._offset_ns = _offset_ns(source)
        self._pose: Triple = (0.0, 0.0, 0.0)
        self._twist: Triple = (0.0, 0.0, 0.0)
        self.last_t_ns: int | None = None
        self.held_speeds: tuple[float, float] = (0.0, 0.0)
        self.state: Any = None
        self.step_state: Any = None
        # Optional aid (an IMU's, see core/odometry/gyro.py): called with every interval about
        # to be integrated, aid(t0_ns, t1_ns, dt_s, twist, speeds at t0, speeds at t1, yaw rate
        # of speeds or None), it returns the twist to integrate instead.
        self.aid: Callable[..., Triple] | None = None

    @property
    def source(self) -> TwistSource:
        """Return the twist source in use (change it with :meth:`set_source`)."""
        return self._source

    @property
    def pose(self) -> np.ndarray:
        """Return the current (x, y, yaw), yaw unwrapped (a new array)."""
        return np.array(self._pose)

    @property
    def held_twist(self) -> np.ndarray:
        """Return the body twist now held (a new array)."""
        return np.array(self._twist)

    @property
    def output_offset_ns(self) -> int:
        """Return the offset (ns) to add to a sample stamp for what is published."""
        return self._offset_ns

    def reset(self, pose=(0.0, 0.0, 0.0)) -> None:
        """Zero (or set) the pose and forget the held speeds and the last stamp."""
        x, y, yaw = (float(v) for v in pose)
        self._pose = (x, y, yaw)
        self.last_t_ns = None
        self._twist = (0.0, 0.0, 0.0)
        self.held_speeds = (0.0, 0.0)
        self.state = None
        self._restart = False

    def restart_pose(self, pose: Triple) -> None:
        """Move the pose to ``pose``; the held speeds, the stamp and any state are kept."""
        x, y, yaw = pose
        self._pose = (float(x), float(y), float(yaw))

    def set_source(self, source: TwistSource, interval: str | None = None) -> None:
        """Switch model (parameters changed at runtime); the held twist is recomputed.

        ``interval`` (None: keep it) switches the convention from the next sample on. A stateful
        source starts afresh from the held speeds (its state is not carried over).
        """
        self._source = source
        if interval is not None:
            self.interval = check_interval(interval)
        self._stateful = is_stateful(source)
        self._deferred = self._stateful and self.interval != 'starting'
        self._offset_ns = _offset_ns(source)
        self.state = None
        self._restart = False
        if self._stateful and self.last_t_ns is not None:
            state, twist = source.begin(None, self.last_t_ns, *self.held_speeds, True)
            if not self._deferred:
                self.state = state
            self._twist = _triple(twist)
            return
        self._twist = _scalar_twist(source, *self.held_speeds)

    def _result(self, status: SampleStatus, dt_s: float = 0.0, detail: str = '') -> StepResult:
        return StepResult(status, self._pose, self._twist, dt_s, detail, self._pose,
                          self._twist)

    def _hold(self, t_ns: int, omega_l: float, omega_r: float, restart: bool = False,
              twist: Triple | None = None) -> None:
        self.last_t_ns = t_ns
        self.held_speeds = (omega_l, omega_r)
        if self._deferred:
            # The state stays at this stamp; begin runs when the next sample ends the interval.
            self._restart = self._restart or restart
            if twist is None:  # nothing integrated up to here: the newest sample's, at rate 0
                _, twist = self.source.begin(self.state, t_ns, omega_l, omega_r, self._restart)
            self._twist = _triple(twist)
            return
        if self._stateful:
            self.state, twist = self.source.begin(self.state, t_ns, omega_l, omega_r, restart)
            self._twist = _triple(twist)
            return
        # ``twist``: these very speeds' twist, already computed (ending): not computed twice
        self._twist = twist if twist is not None else _scalar_twist(self.source, omega_l, omega_r)

    def _interval_twist(self, omega_l: float, omega_r: float, dt_s: float
                        ) -> tuple[Triple, Any]:
        """Return the twist integrated up to a new sample and the source state after it."""
        interval = self.interval
        if self._deferred:
            held_l, held_r = self.held_speeds
            state, _ = self.source.begin(self.state, self.last_t_ns,
                                         interval_speed(held_l, omega_l, interval),
                                         interval_speed(held_r, omega_r, interval),
                                         self._restart)
            state, mean = self.source.advance(state, dt_s)
            return _triple(mean), state
        if self._stateful:
            state, mean = self.source.advance(self.state, dt_s)
            return _triple(mean), state
        if interval == 'starting':
            return self._twist, None
        if interval == 'ending':
            return _scalar_twist(self.source, omega_l, omega_r), None
        held_l, held_r = self.held_speeds
        return _scalar_twist(self.source, interval_speed(held_l, omega_l, interval),
                             interval_speed(held_r, omega_r, interval)), None

    def step(self, t_ns: int, omega_l: float, omega_r: float,
             check_jump: bool = True) -> StepResult:
        """Integrate one sample; ``check_jump`` False: speeds measured by encoder positions."""
        omega_l = float(omega_l)
        omega_r = float(omega_r)
        max_speed = self.limits.max_wheel_speed_rad_s
        if not (abs(omega_l) <= max_speed and abs(omega_r) <= max_speed):  # NaN fails too
            for side, value in (('left', omega_l), ('right', omega_r)):
                if not math.isfinite(value):
                    return self._result(SampleStatus.NON_FINITE_SPEED, detail=(
                        f'{side} wheel speed is {value} (expected a finite rad/s)'))
                if abs(value) > max_speed:
                    return self._result(SampleStatus.IMPLAUSIBLE_SPEED, detail=(
                        f'{side} wheel speed {value:.3g} rad/s exceeds max_wheel_speed '
                        f'{max_speed:g} rad/s'))
        if self.last_t_ns is None:
            self._hold(t_ns, omega_l, omega_r)
            return self._result(SampleStatus.FIRST)
        dt_ns = t_ns - self.last_t_ns
        if dt_ns < 0:
            return self._result(SampleStatus.OLDER_STAMP,
                                detail=f'stamp older than previous by {ns_to_s(-dt_ns):.6f} s')
        dt_s = dt_ns * 1e-9
        if dt_s > self.limits.max_dt_s:
            self._hold(t_ns, omega_l, omega_r, restart=True)
            return self._result(SampleStatus.GAP, dt_s,
                                f'gap of {dt_s:.3f} s > max_dt {self.limits.max_dt_s:g} s: '
                                'not integrated across')
        held_l, held_r = self.held_speeds
        limit = jump_limit(dt_s, self.limits.max_wheel_acceleration_rad_s2)
        if check_jump and not (abs(omega_l - held_l) <= limit and abs(omega_r - held_r) <= limit):
            return self._jump(omega_l, omega_r, dt_s)
        if dt_ns == 0:
            if self._deferred:  # a zero-length interval still runs the source, as in batch
                _, self.state = self._interval_twist(omega_l, omega_r, 0.0)
                self._restart = False
            self._hold(t_ns, omega_l, omega_r)
            return self._result(SampleStatus.DUPLICATE_STAMP,
                                detail='duplicate stamp (dt = 0)')
        step_twist, new_state = self._interval_twist(omega_l, omega_r, dt_s)
        if self.aid is not None:
            step_twist = self.aid(self.last_t_ns, t_ns, dt_s, step_twist, self.held_speeds,
                                  (omega_l, omega_r), None if self._stateful else self._yaw_rate)
        vx, vy, w = step_twist
        start = self._pose
        x, y, theta = start
        if math.isfinite(w * dt_s):  # else numpy's sin would warn; caught just below anyway
            x, y, theta, _, _ = step_scalar(x, y, theta, vx, vy, w, dt_s)
        else:
            theta = math.nan
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(theta)):
            self._hold(t_ns, omega_l, omega_r, restart=True)
            return self._result(SampleStatus.NON_FINITE_STATE, dt_s,
                                'integration produced a non-finite pose; kept the last finite one')
        self._pose = (x, y, theta)
        if self._stateful:
            self.state = new_state
            self.step_state = new_state  # the state whose twist the step integrated
            self._restart = False
        wheels = (interval_speed(held_l, omega_l, self.interval),
                  interval_speed(held_r, omega_r, self.interval))
        if self._deferred:  # the twist the interval ended with (its rate terms included)
            published = self.source.published(new_state)
        elif self.interval == 'ending' and not self._stateful:
            published = step_twist  # these very speeds' twist: not computed twice
        else:
            published = None
        self._hold(t_ns, omega_l, omega_r, twist=published)
        return StepResult(SampleStatus.INTEGRATED, self._pose, self._twist, dt_s, '', start,
                          step_twist, wheels)

    def _yaw_rate(self, omega_l: float, omega_r: float) -> float:
        return _scalar_twist(self._source, omega_l, omega_r)[2]

    def _jump(self, omega_l: float, omega_r: float, dt_s: float) -> StepResult:
        sides = jumped_sides(self.held_speeds, omega_l, omega_r, dt_s,
                             self.limits.max_wheel_acceleration_rad_s2)
        told = ' and '.join(f'{side} wheel speed jumped from {before:.3g} to {after:.3g} rad/s'
                            for side, before, after in sides)
        return self._result(SampleStatus.WHEEL_JUMP, detail=(
            f'{told} in {dt_s:.3f} s (more than max_wheel_acceleration '
            f'{self.limits.max_wheel_acceleration_rad_s2:g} rad/s^2): a glitch of the '
            f'{" and ".join(side for side, _, _ in sides)} wheel reading'))


def _offset_ns(source: TwistSource) -> int:
    """Return a source's output offset in ns (0 for a source without one)."""
    return int(getattr(source, 'output_offset_ns', 0))


def _triple(values: Any) -> Triple:
    """Return three numbers (an array or a sequence) as a tuple of floats."""
    a, b, c = values
    return float(a), float(b), float(c)
