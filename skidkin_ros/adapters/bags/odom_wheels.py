"""Wheel speeds recovered from a drive controller's nav_msgs/Odometry twist.

The rule is :meth:`~skidkin_ros.core.odometry.controller.ControllerGeometry.wheel_speeds`, the
one the node's ``odometry`` input runs, applied message by message so both agree bit for bit.
Stamps are header.stamps (all zero: the receive time); a NaN / infinite twist or a recovered
speed beyond ``max_wheel_speed`` is dropped and counted, as the node refuses it.
"""

from __future__ import annotations

import numpy as np

from skidkin_ros.adapters.bags.common import NoWheelInputError, ODOMETRY, stamp_ns
from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.core.odometry.controller import ControllerGeometry, NonFiniteTwistError
from skidkin_ros.errors import RecordingError


class OdomWheelsMixin:
    """The odometry wheel input of read_wheels, and the message when no wheel input exists."""

    def _read_odometry_wheels(self, topic: str | None, controller: ControllerGeometry | None,
                              max_speed: float) -> WheelSamples:
        chosen = self.select(ODOMETRY, topic, 'wheel speeds (controller odometry)')
        if controller is None:
            raise RecordingError(
                f"wheel speeds from the controller odometry {chosen} need the controller's own "
                'geometry (its wheel_radius and wheel_separation, multipliers included): give '
                '--controller-geometry RADIUS SEPARATION (m) [--controller-multipliers LEFT '
                "RIGHT SEPARATION], as in the controller's parameters")
        stamps: list[int] = []
        receive: list[int] = []
        omega_l: list[float] = []
        omega_r: list[float] = []
        for t_ns, msg in self.messages(chosen):
            twist = msg.twist.twist
            try:
                wl, wr = controller.wheel_speeds(twist.linear.x, twist.angular.z)
            except NonFiniteTwistError:
                self._drop(chosen, 'non-finite twist')
                continue
            if abs(wl) > max_speed or abs(wr) > max_speed:
                self._drop(chosen, f'speed beyond {max_speed:g} rad/s')
                continue
            stamps.append(stamp_ns(msg.header))
            receive.append(t_ns)
            omega_l.append(wl)
            omega_r.append(wr)
        if not stamps:
            raise RecordingError(f'wheel speeds: no usable twist on {chosen} '
                                 f'({self._reasons(chosen)})')
        t = self._header_or_receive(chosen, np.array(stamps, np.int64),
                                    np.array(receive, np.int64))
        keep = self._keep_in_order(chosen, t)
        self.notes.append(
            f'wheel speeds: recovered from the twist of {chosen} with the controller geometry '
            f'r {controller.wheel_radius:g} m x ({controller.left_wheel_radius_multiplier:g}, '
            f'{controller.right_wheel_radius_multiplier:g}), b {controller.wheel_separation:g} '
            f'm x {controller.wheel_separation_multiplier:g} ({int(keep.sum())} samples)')
        self.wheel_input = {'input': 'odometry', 'topic': chosen, **controller.as_values()}
        return WheelSamples(t[keep], np.array(omega_l)[keep], np.array(omega_r)[keep])

    def _no_wheel_input(self) -> None:
        """Raise the error for a recording without JointState nor Float64 wheel topics."""
        odometry = sorted(t for t, m in self.topics().items() if m == ODOMETRY)
        hint = ''
        if odometry:
            hint = (f' The recording has nav_msgs/Odometry ({", ".join(odometry)}): if one is a '
                    "drive controller's odometry (diff_drive_controller), its twist gives the "
                    'wheel speeds: --wheel-odometry TOPIC --controller-geometry RADIUS '
                    "SEPARATION (the controller's configured values, m).")
        raise NoWheelInputError(f'wheel speeds: no sensor_msgs/msg/JointState topic and no pair '
                                f'of std_msgs/Float64 wheel topics in {self.path}. Topics '
                                f'present: {self._listing()}.{hint}')
