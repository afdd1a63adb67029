"""Offline prediction through the node's own integrator, sample for sample.

``skidkin predict`` uses this; the node runs the same ``StreamingIntegrator`` on the same samples,
so a replay of a recording through the node reproduces these poses exactly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.core.odometry.integrator import (IntegratorLimits, SampleStatus,
                                                  StreamingIntegrator, TwistSource)

__all__ = ['Prediction', 'predict_wheels']


@dataclass(frozen=True)
class Prediction:
    """Pose after every wheel sample (x, y, yaw), the held twist, and what happened to it.

    ``t_ns`` are the stamps the node publishes: the sample stamps plus ``offset_ns``, the time
    offset of an augmented model (0 for the five base models).
    """

    t_ns: np.ndarray
    poses: np.ndarray
    twists: np.ndarray
    status: tuple[SampleStatus, ...]
    offset_ns: int = 0

    @property
    def accepted(self) -> np.ndarray:
        return np.array([s.accepted for s in self.status], dtype=bool)


def predict_wheels(wheels: WheelSamples, source: TwistSource,
                   limits: IntegratorLimits | None = None,
                   start: Sequence[float] = (0.0, 0.0, 0.0)) -> Prediction:
    """Run the streaming integrator over every wheel sample, starting at ``start``."""
    integrator = StreamingIntegrator(source, limits or IntegratorLimits())
    integrator.reset(start)
    poses = np.empty((len(wheels), 3))
    twists = np.empty((len(wheels), 3))
    status = []
    for i, (t_ns, omega_l, omega_r) in enumerate(zip(wheels.t_ns, wheels.omega_l,
                                                     wheels.omega_r)):
        result = integrator.step(int(t_ns), omega_l, omega_r)
        poses[i] = result.pose
        twists[i] = result.twist
        status.append(result.status)
    offset_ns = integrator.output_offset_ns
    return Prediction(wheels.t_ns + offset_ns, poses, twists, tuple(status), offset_ns)
