"""Wheel speeds recovered from a drive controller's odometry twist (diff_drive_controller's rule).

Many robots record only their controller's ``nav_msgs/Odometry``. diff_drive_controller computes
its twist as an ideal differential drive with its own configured geometry::

    r_l = wheel_radius * left_wheel_radius_multiplier
    r_r = wheel_radius * right_wheel_radius_multiplier
    b   = wheel_separation * wheel_separation_multiplier
    v   = (omega_l r_l + omega_r r_r) / 2
    w   = (omega_r r_r - omega_l r_l) / b

so the wheel speeds it saw come back exactly from (v, w) and that geometry::

    omega_l = (v - w b / 2) / r_l,   omega_r = (v + w b / 2) / r_r

The controller's geometry is what *it* was configured with, not the robot's true geometry that
the calibration estimates: the recovered speeds are then calibrated like measured ones. This is
the one home of the rule: the node (input ``odometry``) and every offline tool (the bag reader)
call :meth:`ControllerGeometry.wheel_speeds`, so they agree bit for bit.

Caveat: diff_drive_controller publishes the rolling mean of its last
``velocity_rolling_window_size`` (default 10) velocity estimates, so with a window above 1 the
recovered speeds are a moving average and lag the wheels by about half the window.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Mapping

from skidkin_ros.core.kinematics.specs import ParamSpec
from skidkin_ros.errors import ParameterError

__all__ = ['CONTROLLER_SPECS', 'ControllerGeometry', 'NonFiniteTwistError']

PREFIX = 'controller.'
CONTROLLER_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec('wheel_radius', 'm', 0.0, 0.0, 100.0,
              "odometry input: the drive controller's configured wheel_radius (0: not given; "
              'required with input odometry)'),
    ParamSpec('wheel_separation', 'm', 0.0, 0.0, 100.0,
              "odometry input: the drive controller's configured wheel_separation (0: not "
              'given; required with input odometry)'),
    ParamSpec('left_wheel_radius_multiplier', '1', 1.0, 0.0, 100.0,
              "odometry input: the controller's left_wheel_radius_multiplier", lower_open=True),
    ParamSpec('right_wheel_radius_multiplier', '1', 1.0, 0.0, 100.0,
              "odometry input: the controller's right_wheel_radius_multiplier",
              lower_open=True),
    ParamSpec('wheel_separation_multiplier', '1', 1.0, 0.0, 100.0,
              "odometry input: the controller's wheel_separation_multiplier", lower_open=True),
)


class NonFiniteTwistError(ValueError):
    """A twist with NaN or infinity: no wheel speed can be recovered from it."""


@dataclass(frozen=True)
class ControllerGeometry:
    """The geometry a diff_drive_controller was configured with (m, multipliers unitless)."""

    wheel_radius: float
    wheel_separation: float
    left_wheel_radius_multiplier: float = 1.0
    right_wheel_radius_multiplier: float = 1.0
    wheel_separation_multiplier: float = 1.0

    def __post_init__(self) -> None:
        missing = [name for name in ('wheel_radius', 'wheel_separation')
                   if not (isinstance(getattr(self, name), (int, float))
                           and math.isfinite(getattr(self, name)) and getattr(self, name) > 0)]
        if missing:
            raise ParameterError(
                "the odometry wheel input needs the drive controller's own geometry: "
                + ', '.join(f'{PREFIX}{name} (m, > 0; got {getattr(self, name)!r})'
                            for name in missing)
                + '. Copy wheel_radius and wheel_separation (and the multipliers) from the '
                "controller's parameters (e.g. `ros2 param get /diff_drive_controller "
                'wheel_radius`); on the command line --controller-geometry RADIUS SEPARATION')
        for name in ('left_wheel_radius_multiplier', 'right_wheel_radius_multiplier',
                     'wheel_separation_multiplier'):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ParameterError(f'{PREFIX}{name} must be a finite number > 0, got '
                                     f'{value!r}')

    @classmethod
    def from_values(cls, values: Mapping[str, Any]) -> 'ControllerGeometry':
        """Return the geometry from flat ``controller.*`` values (node parameters)."""
        return cls(**{spec.name: float(values.get(PREFIX + spec.name, spec.default))
                      for spec in CONTROLLER_SPECS})

    def as_values(self) -> dict[str, float]:
        """Return the flat ``controller.*`` values (what a parameters file records)."""
        return {PREFIX + spec.name: float(getattr(self, spec.name)) for spec in CONTROLLER_SPECS}

    def wheel_speeds(self, v_m_s: float, w_rad_s: float) -> tuple[float, float]:
        """Return (omega_l, omega_r) in rad/s that give the controller's twist (v, w).

        Raise NonFiniteTwistError for a NaN or infinite v or w.
        """
        v, w = float(v_m_s), float(w_rad_s)
        if not (math.isfinite(v) and math.isfinite(w)):
            raise NonFiniteTwistError(f'twist linear.x {v!r} m/s, angular.z {w!r} rad/s is not '
                                      'finite')
        half = 0.5 * w * self.wheel_separation * self.wheel_separation_multiplier
        return ((v - half) / (self.wheel_radius * self.left_wheel_radius_multiplier),
                (v + half) / (self.wheel_radius * self.right_wheel_radius_multiplier))

    def twist(self, omega_l: float, omega_r: float) -> tuple[float, float]:
        """Return the controller's (v, w) for wheel speeds, as diff_drive_controller does."""
        left = omega_l * self.wheel_radius * self.left_wheel_radius_multiplier
        right = omega_r * self.wheel_radius * self.right_wheel_radius_multiplier
        return ((left + right) / 2.0,
                (right - left) / (self.wheel_separation * self.wheel_separation_multiplier))
