"""How the node's callbacks run: never fatal, and each input with a QoS profile of its own."""

from __future__ import annotations

import copy
import functools
from typing import Any, Callable

from rclpy.qos import qos_profile_sensor_data, QoSProfile

__all__ = ['guarded', 'sensor_qos']


def sensor_qos() -> QoSProfile:
    """Return a fresh copy of the sensor-data profile for one input.

    QoS overrides (``qos_overrides.<topic>...``) change the profile they are given in place, and
    rclpy's ``qos_profile_sensor_data`` is one object shared by every node of the process.
    """
    return copy.copy(qos_profile_sensor_data)


def guarded(method: Callable) -> Callable:
    """Wrap a callback so an unexpected exception is counted and logged, never fatal (N15)."""
    @functools.wraps(method)
    def wrapper(self: Any, *args: Any) -> Any:
        try:
            return method(self, *args)
        except Exception as err:  # noqa: B902 - a callback must never kill the node
            self._callback_failed(method.__name__, err)
            return None
    return wrapper
