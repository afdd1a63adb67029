"""Online calibration: is the reference's heading measured? (a mixin of OnlineCalibrator).

A GNSS receiver turned into nav_msgs/Odometry (robot_localization's navsat_transform,
gps_common's utm_odometry) publishes a good position and no heading: an identity (or constant)
orientation, its variance in the pose covariance set huge (999, 99999) or left 0. Learning from
such a pose compares the wheels' turning with a heading that never turns: every segment says the
yaw parameters are wrong, and the odometry is ruined within a minute (fault matrix N172).

``online.reference_heading`` decides:

* ``measured``: the heading is used as it comes (what the learner always did);
* ``unmeasured``: no pose is learned from (counted ``reference_no_heading``);
* ``auto`` (default): the heading is taken as not measured from the first pose whose yaw
  variance (pose.covariance[35]) is ``HEADING_VARIANCE`` or more (or negative: the -1 that
  sensor_msgs uses for "no data"), or once the heading has stayed
  constant (within ``HEADING_FLAT``) while the wheels turned ``HEADING_TURN`` and the position
  moved (a measured heading is never constant while the robot turns; a pose repeated whole is
  a frozen reference, the stall gate's). Until then a segment over which the heading stayed
  constant is not learned from (``online_heading_constant``): its start heading may be
  the converter's constant, not the robot's.

Once not measured, it stays so (the decision is logged, with its cause, and named on
/diagnostics as ``online.reference_heading``): every later pose is counted
``reference_no_heading``; by the covariance, until ``HEADING_CONFIRM`` poses in a row have a
yaw variance under ``HEADING_VARIANCE`` (a localizer that was lost: measured again, logged).
A heading found constant stays not measured until ``online.*`` changes or the node restarts.
With ``online.position_only`` its position is learned from
(:mod:`skidkin_ros.core.online.position`); without it (the default) the pose is not used, the
state is ``holding``, and the odometry goes on with the parameters in force.
"""

from __future__ import annotations

from skidkin_ros.core.odometry.reference import ReferenceStatus

__all__ = ['HeadingRule', 'HEADING_VARIANCE', 'HEADING_TURN']

# A yaw variance (rad^2) from which the heading is not a heading (1 rad = 57 degrees).
HEADING_VARIANCE = 1.0
# Wheel turning (rad, the model's yaw, range over the run) with a constant reference heading
# that shows the heading is not measured.
HEADING_TURN = 0.3
# A heading within this (rad) of the run's first is constant: a converter's constant passed
# through float32 or a transform jitters by ~1e-7 (a measured one moves by its noise, >= 1e-4).
HEADING_FLAT = 1e-5
# Poses in a row with a yaw variance under HEADING_VARIANCE after which a heading judged not
# measured by its covariance is measured again (a localizer lost for a while, AMCL's global
# localization: its variance is huge until it converges).
HEADING_CONFIRM = 5


class HeadingRule:
    """Whether the reference's heading is measured (module docstring); a mixin."""

    # why the heading is taken as not measured: '' (it is, or nothing says otherwise yet),
    # 'configured', 'covariance' or 'constant'
    no_heading = ''
    # the run of poses with one exact heading: [first pose's wheel time, yaw, last judged pose's
    # wheel time, wheel turn since the first, its minimum, its maximum]
    _flat: list | None = None
    _measured_run = 0   # poses in a row with a yaw variance under HEADING_VARIANCE

    def heading_state(self) -> str:
        """Return what /diagnostics reports as online.reference_heading."""
        if self.no_heading:
            return f'unmeasured ({self.no_heading})'
        return self.params.reference_heading

    def _heading_refused(self, yaw_variance: float) -> bool:
        """On arrival: True (counted, not used) when the heading is not measured."""
        mode = self.params.reference_heading
        if mode == 'measured':
            return False
        if self.no_heading == 'covariance':
            self._measured_run = (self._measured_run + 1
                                  if 0.0 <= yaw_variance < HEADING_VARIANCE else 0)
            if self._measured_run >= HEADING_CONFIRM:
                self._heading_measured_again()
        if not self.no_heading:
            if mode == 'unmeasured':
                self._declare_no_heading('configured', 'online.reference_heading is unmeasured')
            elif yaw_variance >= HEADING_VARIANCE or yaw_variance < 0.0:   # NaN: none given
                self._declare_no_heading('covariance', f'its yaw variance is {yaw_variance:g} '
                                         f'rad^2 (>= {HEADING_VARIANCE:g}, or negative as in '
                                         'sensor_msgs\' "no data": no heading)')
        if not self.no_heading:
            return False
        self.counters[ReferenceStatus.NO_HEADING.value] += 1
        self.last_refusal = ReferenceStatus.NO_HEADING.value
        return True

    def _heading_flat(self, t_ns: int, x: float, y: float, yaw: float) -> bool:
        """Judge the heading's run (auto): True when it shows the heading is not measured.

        A pose equal to the last one judged (position and heading: a frozen reference, a SLAM
        lost while the robot turns on the spot) is the stall gate's: its wheel turn is not
        counted until the position moves again.
        """
        if self.params.reference_heading != 'auto' or self.no_heading:
            return False
        flat = self._flat
        if flat is None or abs(yaw - flat[1]) > HEADING_FLAT:
            self._flat = [t_ns, yaw, t_ns, 0.0, 0.0, 0.0, x, y]
            return False
        if x == flat[6] and y == flat[7]:   # frozen: not a heading's evidence
            return False
        moved = self._steps.motion(flat[2], t_ns)
        if moved is None:   # a wheel gap: the run starts again
            self._flat = [t_ns, yaw, t_ns, 0.0, 0.0, 0.0, x, y]
            return False
        flat[6], flat[7] = x, y
        flat[2] = t_ns
        flat[3] += moved[1]
        flat[4] = min(flat[4], flat[3])
        flat[5] = max(flat[5], flat[3])
        if flat[5] - flat[4] < HEADING_TURN:
            return False
        self._declare_no_heading('constant', f'its heading stayed {yaw:+.4f} rad while the '
                                 f'wheels turned {flat[5] - flat[4]:.2f} rad over '
                                 f'{(t_ns - flat[0]) * 1e-9:.1f} s')
        self._seg_start = None
        self._refs.clear()
        self.counters[ReferenceStatus.NO_HEADING.value] += 1
        self.last_refusal = ReferenceStatus.NO_HEADING.value
        return True

    def _heading_constant_over(self, t_a_ns: int, yaw_a: float, yaw_b: float) -> bool:
        """Return True (auto) when the heading stayed exactly constant from t_a_ns on."""
        flat = self._flat
        return (self.params.reference_heading == 'auto' and flat is not None
                and abs(yaw_a - yaw_b) <= HEADING_FLAT and abs(yaw_a - flat[1]) <= HEADING_FLAT
                and flat[0] <= t_a_ns)

    def _probe(self, ref) -> None:
        """Leave out the segment in progress when its heading stayed exactly constant."""
        start = self._seg_start
        if start is not None and self._heading_constant_over(start.t_ns, start.yaw, ref.yaw):
            return
        super()._probe(ref)

    def _heading_measured_again(self) -> None:
        """Take the heading as measured again (by the covariance): learn from full poses."""
        self.no_heading = ''
        self._measured_run = 0
        self._flat = None
        self._seg_start = None   # a position-only segment's start has no heading
        self._refs.clear()
        self._positions = None
        self._warn('reference_heading_measured', "online calibration: the reference's yaw "
                   f'variance stayed under {HEADING_VARIANCE:g} rad^2 for {HEADING_CONFIRM} '
                   'poses: its heading is measured again and learned from')

    def _declare_no_heading(self, cause: str, why: str) -> None:
        self.no_heading = cause
        self._measured_run = 0
        self._warn(ReferenceStatus.NO_HEADING.value,
                   f'online calibration: the reference has no measured heading ({why}); its '
                   'heading is never learned from (counted reference_no_heading). '
                   + ('Learning from its positions alone (online.position_only).'
                      if self.position_learning() else
                      'Its poses are not used: the odometry goes on with the parameters in '
                      'force (online.position_only: true learns from the positions alone). ')
                   + 'Set online.reference_heading: measured only if the heading is real')
