"""Wheel speeds from what drivers publish: the rules the node and the bag reader share.

A robot reports its wheels in one of two ways, and both the live node and the offline tools must
turn them into the same (t, omega_left, omega_right) samples, or replaying a recording through the
node would not reproduce the offline prediction:

1. A sensor_msgs/JointState listing every joint: find the wheel joints in the ``name`` list
   (:func:`joint_indices`, once per distinct list: drivers repeat it; a wheel joint listed twice
   is refused, as its speed would be a guess, and :func:`repeated_names` names any other joint
   listed twice, for a warning), check there is a velocity
   per name (:func:`check_velocity_count`), and take each side's speed as the mean of its joints'
   velocities (:func:`side_speed`; identical values come back unchanged, so a single encoder per
   side survives the mean bit for bit).
2. Two std_msgs/Float64 topics, one per side, without a stamp: a left and a right value are
   paired when they arrive within ``pair_tolerance`` of each other and stamped with the later
   receive time (:class:`WheelPairer`); a value whose partner does not come in time is dropped.
   The node feeds it as messages arrive; :func:`pair_wheel_streams` feeds it a recording's
   messages in receive order.
3. A wheel speed that jumps is a glitch (a driver's spike, a bit flip), even below
   ``max_wheel_speed``: a sample whose speed changed faster than ``max_wheel_acceleration`` from
   the last accepted one, measured over at least ``MIN_JUMP_INTERVAL_S`` (so encoder quantization
   at kHz rates does not trip it), is rejected (:func:`jumped_sides`). The node's integrator
   rejects it as it comes; the bag reader drops it with :func:`drop_jumps`, so neither a fit nor
   the lidar ground truth's check against the wheels ever sees a spike. The reference is the last
   accepted sample, so a real step in speed is taken after at most |step| / max_wheel_acceleration
   seconds; the first sample (and the first after a gap longer than ``max_dt``) has no reference
   and is taken as it is.

4. Encoder positions (``wheel_signal``, :class:`WheelSignal`): with ``position``, a side's speed
   over [t_k-1, t_k] is its travel (the difference of its joints' positions, the mean over its
   joints) divided by the interval: what diff_drive_controller integrates, and exactly what the
   ``ending`` sample-interval convention means. A joint whose two positions both lie within one
   turn of zero (drivers that wrap continuous joints into [-pi, pi) or [0, 2 pi)) and differ by
   more than half a turn has wrapped: its travel is taken the short way round. A side whose
   speed would exceed ``max_wheel_speed`` is rejected like a bad speed, and the differences start
   again from the new positions (a driver that reset its counters is followed, not refused
   forever); a non-finite position is rejected and the last good one kept, and so is one beyond
   ``POSITION_LIMIT_RAD``, where float64 no longer resolves a count (at 1e16 rad neighbouring
   floats are 2 rad apart: every travel would read 0). Positions that stay put while the
   velocities say the wheel turned more than ``STALE_TRAVEL_RAD`` (a quarter turn: every encoder
   counts more often) are frozen: ``position`` keeps integrating them (the user chose them) and
   warns once (cause ``stale_position``).

   ``auto`` measures the distance as ``position`` does wherever the positions are usable. Real
   encoders are quantised: between two counts the position repeats while the wheel turns, and the
   count that follows holds travel of several intervals. So once auto integrates positions, a
   repeated position is zero travel, as under ``position``, never a switch to the velocity (that
   counted the same travel twice: once by the velocity, once by the next count). The velocities
   are integrated only where the positions cannot measure: a message without positions, a
   non-finite or unresolvable one (the reference is then dropped), positions that never changed
   yet (a driver that does not fill them), and frozen positions as above (said once). Back from
   the velocities, the first changed position starts a new reference and its interval is still
   measured by the velocity (the count it holds was partly integrated already), unless the
   reference is the previous sample. auto says which signal it uses when that changes; an
   interval is always measured by one signal.

Times are integer nanoseconds; speeds rad/s.
"""

from __future__ import annotations

import enum
import math
from typing import Iterable, NamedTuple, Sequence

from skidkin_ros.core.kinematics.augmented import MIN_RATE_STEP_S
from skidkin_ros.errors import brief

__all__ = [
    'SIDES',
    'MissingJointError',
    'DuplicateJointError',
    'MalformedMessageError',
    'joint_indices',
    'repeated_names',
    'check_velocity_count',
    'side_speed',
    'speeds_at',
    'Pairing',
    'WheelPairer',
    'pair_wheel_streams',
    'MIN_JUMP_INTERVAL_S',
    'jump_limit',
    'jumped_sides',
    'drop_jumps',
    'WHEEL_SIGNALS',
    'check_position_count',
    'positions_at',
    'SignalResult',
    'WheelSignal',
    'POSITION_LIMIT_RAD',
    'STALE_TRAVEL_RAD',
]

WHEEL_SIGNALS = ('velocity', 'position', 'auto')

SIDES = ('left', 'right')
# Wheel accelerations are measured over at least this long (s): at kHz rates one encoder count
# between two samples is a large acceleration, not a glitch. The same floor as a rate term's.
MIN_JUMP_INTERVAL_S = MIN_RATE_STEP_S
# Beyond this |position| (rad), neighbouring float64 values are more than 1e-6 rad apart: a
# count (1e-3 rad at 4096 counts per turn) is no longer resolved (the yaw limit's reasoning).
POSITION_LIMIT_RAD = 1e-6 / 2.220446049250313e-16
# Positions that do not change while the velocities integrate more than this (rad, a quarter
# turn) are frozen: an encoder with four counts per turn or more changes within it.
STALE_TRAVEL_RAD = math.pi / 2
# Longest text of a name list echoed in a message (a hostile list may hold millions of names).
NAMES_SHOWN_CHARS = 400


class MalformedMessageError(ValueError):
    """A message whose fields contradict each other (e.g. fewer velocities than names)."""


class MissingJointError(ValueError):
    """A JointState that lacks one of the configured wheel joints."""


class DuplicateJointError(ValueError):
    """A JointState that lists one of the configured wheel joints more than once."""


def joint_indices(names: Sequence[str], left_joints: Sequence[str],
                  right_joints: Sequence[str]) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Return where the left and right wheel joints are in a JointState's ``name`` list.

    Raises MissingJointError when a configured joint is absent, DuplicateJointError when one
    is listed twice (two velocities for one wheel: which is right cannot be told). Drivers send
    the same name list every time, so callers look the indices up once per distinct list.
    """
    index = {name: i for i, name in enumerate(names)}
    wheels = (*left_joints, *right_joints)
    missing = [joint for joint in wheels if joint not in index]
    if missing:
        raise MissingJointError(
            f'JointState lacks wheel joint(s) {missing} (it has {len(names)}: '
            f'{brief(list(names), NAMES_SHOWN_CHARS)}); check left_wheel_joints / '
            'right_wheel_joints')
    twice = [joint for joint in repeated_names(names) if joint in wheels]
    if twice:
        where = '; '.join(f'{joint!r} at {[i for i, n in enumerate(names) if n == joint]}'
                          for joint in twice)
        raise DuplicateJointError(
            f'JointState lists wheel joint(s) more than once ({where}): which velocity is the '
            "wheel's cannot be told, sample rejected; fix the driver so that each joint is "
            'listed once')
    return (tuple(index[joint] for joint in left_joints),
            tuple(index[joint] for joint in right_joints))


def repeated_names(names: Sequence[str]) -> list[str]:
    """Return the names listed more than once, each once, in the order they repeat."""
    seen: set[str] = set()
    repeated: dict[str, None] = {}
    for name in names:
        if name in seen:
            repeated[name] = None
        seen.add(name)
    return list(repeated)


def check_velocity_count(n_names: int, n_velocities: int) -> None:
    """Raise MalformedMessageError when a JointState has fewer velocities than names."""
    if n_velocities < n_names:
        raise MalformedMessageError(
            f'JointState has {n_names} names but only {n_velocities} velocities; expected '
            'one velocity (rad/s) per joint name')


def side_speed(values: Sequence[float]) -> float:
    """Return the mean of one side's wheel speeds (rad/s), correctly rounded (math.fsum).

    Identical values return that value unchanged, so a single-wheel reading survives the mean
    bit for bit.
    """
    first = float(values[0])
    if all(float(v) == first for v in values):
        return first
    return math.fsum(float(v) for v in values) / len(values)


def speeds_at(velocity: Sequence[float], left: Sequence[int],
              right: Sequence[int]) -> tuple[float, float]:
    """Return (omega_left, omega_right) in rad/s: each the mean of its joints' velocities."""
    return side_speed([velocity[i] for i in left]), side_speed([velocity[i] for i in right])


class Pairing(enum.Enum):
    """What :meth:`WheelPairer.offer` did with one side's value."""

    PAIRED = 'paired'      # it completed a pair: (t, omega_l, omega_r) is returned
    WAITING = 'waiting'    # it waits for the other side
    UNPAIRED = 'unpaired'  # it waits, and an earlier value was dropped: its partner came too late


class WheelPairer:
    """Pair a left and a right wheel speed that arrive as two unstamped streams.

    ``offer(side, t_ns, omega)`` with ``t_ns`` the receive time: when the other side has a value
    waiting received within ``tolerance_ns``, both form a sample stamped with the later of the two
    times. Otherwise the value waits; if this side already had one waiting, or the other side's
    waiting value is too old, that earlier value is dropped (UNPAIRED).
    """

    def __init__(self, tolerance_ns: float) -> None:
        self.tolerance_ns = tolerance_ns
        self._pending: dict[str, tuple[int, float] | None] = {'left': None, 'right': None}
        self.last_seen_ns: dict[str, int | None] = {'left': None, 'right': None}

    def clear(self) -> None:
        """Drop the values waiting for a partner (after a reset)."""
        self._pending = {'left': None, 'right': None}

    def offer(self, side: str, t_ns: int, omega: float
              ) -> tuple[Pairing, tuple[int, float, float] | None]:
        """Take one side's value; return what happened and the sample it completed, if any."""
        other = 'right' if side == 'left' else 'left'
        self.last_seen_ns[side] = t_ns
        tolerance_ns = self.tolerance_ns
        partner = self._pending[other]
        if partner is not None and abs(t_ns - partner[0]) <= tolerance_ns:
            self._pending[other] = None
            t_pair = max(t_ns, partner[0])
            if side == 'left':
                return Pairing.PAIRED, (t_pair, omega, partner[1])
            return Pairing.PAIRED, (t_pair, partner[1], omega)
        outcome = (Pairing.UNPAIRED if self._pending[side] is not None or partner is not None
                   else Pairing.WAITING)
        self._pending[side] = (t_ns, omega)
        if partner is not None and t_ns - partner[0] > tolerance_ns:
            self._pending[other] = None
        return outcome, None


def pair_wheel_streams(messages: Iterable[tuple[str, int, float]], tolerance_ns: float
                       ) -> tuple[list[tuple[int, float, float]], int]:
    """Pair a recording's (side, receive ns, omega) messages, in receive order, as the node does.

    Returns the samples (t_ns, omega_l, omega_r) and the number of UNPAIRED events.
    """
    pairer = WheelPairer(tolerance_ns)
    samples = []
    unpaired = 0
    for side, t_ns, omega in messages:
        outcome, sample = pairer.offer(side, t_ns, omega)
        if sample is not None:
            samples.append(sample)
        elif outcome is Pairing.UNPAIRED:
            unpaired += 1
    return samples, unpaired


def jump_limit(dt_s: float, max_acceleration: float) -> float:
    """Return the largest plausible change of a wheel speed (rad/s) over ``dt_s`` seconds."""
    return max_acceleration * (dt_s if dt_s > MIN_JUMP_INTERVAL_S else MIN_JUMP_INTERVAL_S)


def jumped_sides(held: tuple[float, float], omega_l: float, omega_r: float, dt_s: float,
                 max_acceleration: float) -> list[tuple[str, float, float]]:
    """Return (side, from, to) for each side whose speed jumped beyond :func:`jump_limit`."""
    limit = jump_limit(dt_s, max_acceleration)
    return [(side, before, after)
            for side, before, after in (('left', held[0], omega_l), ('right', held[1], omega_r))
            if abs(after - before) > limit]


def drop_jumps(t_ns: Sequence[int], omega_l: Sequence[float], omega_r: Sequence[float],
               max_acceleration: float, max_dt_s: float,
               by_position: Sequence[bool] | None = None) -> tuple[list[bool], dict[str, int]]:
    """Return which samples to keep (stamps increasing) and how many jumps each side had.

    The integrator's rule, run over a recording: a sample that jumps from the last kept one is
    dropped; after a gap longer than ``max_dt_s`` the next sample is kept as it is. Samples
    ``by_position`` (speeds measured by encoder positions) are never dropped, and are the
    reference of the next one, as in the node.
    """
    keep = []
    sides = {'left': 0, 'right': 0}
    last_t: int | None = None
    held = (0.0, 0.0)
    exempt = [False] * len(t_ns) if by_position is None else list(by_position)
    for t, wl, wr, measured in zip(t_ns, omega_l, omega_r, exempt):
        t = int(t)
        if last_t is not None and not measured and (t - last_t) * 1e-9 <= max_dt_s:
            jumped = jumped_sides(held, wl, wr, (t - last_t) * 1e-9, max_acceleration)
            if jumped:
                for side, _, _ in jumped:
                    sides[side] += 1
                keep.append(False)
                continue
        keep.append(True)
        last_t, held = t, (float(wl), float(wr))
    return keep, sides


def check_position_count(n_names: int, n_positions: int) -> bool:
    """Return whether a JointState carries positions (none, or one per name; else raise)."""
    if n_positions == 0:
        return False
    if n_positions != n_names:
        raise MalformedMessageError(
            f'JointState has {n_names} names but {n_positions} positions; expected none or one '
            'position (rad) per joint name')
    return True


def positions_at(position: Sequence[float], left: Sequence[int], right: Sequence[int]
                 ) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Return the left and right wheel joints' positions (rad), as floats."""
    return (tuple(float(position[i]) for i in left), tuple(float(position[i]) for i in right))


def _travel(before: float, after: float) -> float:
    """Return a joint's travel (rad) between two positions, a wrap taken the short way round."""
    travel = after - before
    if abs(travel) > math.pi and abs(before) <= 2 * math.pi and abs(after) <= 2 * math.pi:
        travel -= 2 * math.pi * round(travel / (2 * math.pi))
    return travel


class SignalResult(NamedTuple):
    """What :meth:`WheelSignal.take` made of one sample.

    ``speeds``: (omega_l, omega_r) to integrate, or None when the sample is rejected (``cause``:
    'no_position', 'non_finite', 'position_range' or 'implausible', with ``detail``);
    ``switched``: the signal now in use, when it changed with this sample; ``warning``: a
    (cause, message) to report about an accepted sample (frozen positions); ``by_position``:
    the speeds are a travel between positions (the jump rule is not theirs: one encoder count
    over a short interval is a large change of speed, not a glitch).
    """

    speeds: tuple[float, float] | None
    cause: str = ''
    detail: str = ''
    switched: str = ''
    warning: tuple[str, str] | None = None
    by_position: bool = False


def _usable(positions: tuple[Sequence[float], Sequence[float]] | None) -> str:
    """Return why positions cannot measure travel ('' when they can)."""
    if positions is None:
        return 'no_position'
    for side in positions:
        for v in side:
            if not math.isfinite(v):
                return 'non_finite'
            if abs(v) > POSITION_LIMIT_RAD:
                return 'position_range'
    return ''


class WheelSignal:
    """Turn a wheel sample (velocities and, maybe, positions) into speeds (module docstring, 4).

    ``take(t_ns, omega_l, omega_r, positions)`` with ``positions`` = (left joints' positions,
    right joints' positions) or None. ``in_use`` says which signal measured the last interval.
    """

    def __init__(self, mode: str = 'velocity', max_speed_rad_s: float = math.inf) -> None:
        if mode not in WHEEL_SIGNALS:
            raise ValueError(f'wheel_signal must be one of {", ".join(WHEEL_SIGNALS)}, got '
                             f'{mode!r}')
        self.mode = mode
        self.max_speed_rad_s = max_speed_rad_s
        self.in_use = 'position' if mode == 'position' else 'velocity'
        self._reference: tuple[int, tuple[float, ...], tuple[float, ...]] | None = None
        self._speeds = (0.0, 0.0)
        # Frozen-position watch: the last stamp, the velocities' travel (rad per side) since the
        # positions last changed, and whether that was already reported.
        self._last_t_ns: int | None = None
        self._unmeasured = [0.0, 0.0]
        self._frozen = False

    def clear(self) -> None:
        """Forget the position reference (after a reset, a clock change or new joints)."""
        self._reference = None
        self._last_t_ns = None
        self._unmeasured = [0.0, 0.0]
        self._frozen = False

    def _use(self, signal: str) -> str:
        if signal == self.in_use:
            return ''
        self.in_use = signal
        return signal

    def take(self, t_ns: int, omega_l: float, omega_r: float,
             positions: tuple[Sequence[float], Sequence[float]] | None) -> SignalResult:
        mode = self.mode
        if mode == 'velocity':
            return SignalResult((omega_l, omega_r))
        why = _usable(positions)
        if why:
            if mode == 'auto':
                self.clear()
                return SignalResult((omega_l, omega_r), switched=self._use('velocity'))
            return SignalResult(None, why, _UNUSABLE[why].format(positions=positions,
                                                                 limit=POSITION_LIMIT_RAD))
        left, right = tuple(positions[0]), tuple(positions[1])
        previous_t = self._last_t_ns
        frozen = self._watch(t_ns, omega_l, omega_r, left, right)
        if mode == 'position':
            result = self._difference(t_ns, omega_l, omega_r, left, right)
            if frozen:
                return result._replace(warning=('stale_position', frozen))
            return result
        return self._auto(t_ns, omega_l, omega_r, left, right, previous_t, frozen)

    def _watch(self, t_ns: int, omega_l: float, omega_r: float, left: tuple[float, ...],
               right: tuple[float, ...]) -> str:
        """Track the velocities' travel while the positions stay put; say when they froze."""
        reference = self._reference
        last = self._last_t_ns
        if last is None or t_ns > last:
            self._last_t_ns = t_ns
        if reference is None or (left, right) != (reference[1], reference[2]):
            self._unmeasured = [0.0, 0.0]
            self._frozen = False
            return ''
        if last is None or t_ns <= last:
            return ''
        dt_s = (t_ns - last) * 1e-9
        for k, omega in enumerate((omega_l, omega_r)):
            if math.isfinite(omega):
                self._unmeasured[k] += omega * dt_s
        travel = max(abs(v) for v in self._unmeasured)
        if self._frozen or not travel > STALE_TRAVEL_RAD:
            return ''
        self._frozen = True
        return (f'wheel joint positions {list(left)} / {list(right)} rad have not changed while '
                f'the wheel velocities say the wheels turned {travel:.3g} rad (more than '
                f'{STALE_TRAVEL_RAD:.3g} rad, a quarter turn): the encoder positions look frozen')

    def _auto(self, t_ns: int, omega_l: float, omega_r: float, left: tuple[float, ...],
              right: tuple[float, ...], previous_t: int | None, frozen: str) -> SignalResult:
        reference = self._reference
        if reference is None:  # nothing to difference yet: the velocities measure
            self._reference = (t_ns, left, right)
            return SignalResult((omega_l, omega_r), switched=self._use('velocity'))
        changed = (left, right) != (reference[1], reference[2])
        if self.in_use == 'position':
            if frozen:   # the positions froze: the velocities measure until they move again
                return SignalResult((omega_l, omega_r), switched=self._use('velocity'),
                                    warning=('stale_position', frozen + '; wheel_signal auto '
                                             'integrates the velocities until they change'))
            return self._difference(t_ns, omega_l, omega_r, left, right)
        if not changed:
            return SignalResult((omega_l, omega_r))
        if reference[0] != previous_t:
            # The count this sample adds was partly integrated by the velocities already.
            self._reference = (t_ns, left, right)
            return SignalResult((omega_l, omega_r), switched=self._use('position'))
        return self._difference(t_ns, omega_l, omega_r, left, right)

    def _difference(self, t_ns: int, omega_l: float, omega_r: float, left: tuple[float, ...],
                    right: tuple[float, ...]) -> SignalResult:
        reference = self._reference
        if reference is None:  # the first positions: nothing to difference yet
            self._reference = (t_ns, left, right)
            speeds = tuple(v if math.isfinite(v) else 0.0 for v in (omega_l, omega_r))
            return SignalResult(speeds, switched=self._use('position'))
        dt_ns = t_ns - reference[0]
        if dt_ns <= 0:  # a duplicate or older stamp: the integrator says which, and skips it
            return SignalResult(self._speeds, by_position=True)
        dt_s = dt_ns * 1e-9
        speeds = []
        for side, before, after in (('left', reference[1], left), ('right', reference[2], right)):
            speed = side_speed([_travel(b, a) / dt_s for b, a in zip(before, after)])
            if not abs(speed) <= self.max_speed_rad_s:
                self._reference = (t_ns, left, right)
                return SignalResult(None, 'implausible', (
                    f'{side} wheel position jumped from {list(before)} to {list(after)} rad in '
                    f'{dt_s:.3f} s ({speed:.3g} rad/s, beyond max_wheel_speed '
                    f'{self.max_speed_rad_s:g} rad/s); sample rejected, positions differenced '
                    'from the new ones on'))
            speeds.append(speed)
        self._reference = (t_ns, left, right)
        self._speeds = (speeds[0], speeds[1])
        return SignalResult(self._speeds, switched=self._use('position'), by_position=True)


_UNUSABLE = {
    'no_position': ('JointState has no positions but wheel_signal is position; sample rejected: '
                    'publish the joint positions, or set wheel_signal to velocity or auto'),
    'non_finite': ('wheel joint positions {positions} are not all finite (expected finite rad); '
                   'sample rejected, the last finite positions kept'),
    'position_range': ('wheel joint positions {positions} lie beyond {limit:.3g} rad, where '
                       'float64 no longer resolves an encoder count (every travel would read '
                       '0); sample rejected: make the driver wrap or reset its counters'),
}
