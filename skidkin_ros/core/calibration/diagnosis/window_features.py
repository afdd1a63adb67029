"""The residual model's terms as the velocity target sees them: integrated, then differentiated.

The regression's target at a pose (:func:`~.residuals.pose_residuals`) is not the body twist
at that instant: it is the slope of a local quadratic fitted to the poses within +-``window``,
ground truth minus model. A correction C phi(z) added to the model's twist moves the model's
poses by its integral, and the target by the same differentiator applied to that integral. So
the term a coefficient meets at pose i is not phi(z_i) but

    D[integral of R(theta) phi dt](i), turned into the body frame at the pose's heading,

D the differentiator's slope weights at the pose. For a yaw-rate coefficient that is D applied to
the plain integral; for a forward or lateral one, to the integral of phi rotated by the
model's heading (both give the same body-frame value for their own component; the coupling
into the other translational component is left out). The two agree with phi(z_i) where z is
constant over the window; where it changes within the window (turns, accelerations) the plain
phi(z_i) is biased, and the more the longer the window. With these terms the target can be
taken over a longer window (less ground-truth noise) without that bias.

One row per wheel sample: the twist the residual model sees (its inputs, as
:func:`~.regression.model_inputs` has them at the poses), the step each interval is integrated
for (:func:`~skidkin_ros.core.odometry.integrator.stream_twists`) and the model's heading
(:func:`~skidkin_ros.core.odometry.integrator.rollout_stream`).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from skidkin_ros.core.calibration.diagnosis.options import DiagnosisOptions
from skidkin_ros.core.calibration.diagnosis.residuals import (base_rates, body_velocities,
                                                              difference_operator, integrated,
                                                              PoseSamples, truth_velocities)
from skidkin_ros.core.calibration.engine import TwistSource
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.kinematics import residual
from skidkin_ros.core.kinematics.augmented import BoundAugmented
from skidkin_ros.core.kinematics.extensions import get_extension
from skidkin_ros.core.odometry.integrator import rollout_stream, stream_twists

__all__ = ['window_terms']


def _incoming(source: TwistSource, wl: np.ndarray, wr: np.ndarray, t_s: np.ndarray,
              rate: np.ndarray) -> np.ndarray:
    """Return the twist the residual model sees: the base twist through the stages before it."""
    base = source.base if isinstance(source, BoundAugmented) else source
    twist = np.asarray(base.twist(wl, wr), dtype=float)
    if isinstance(source, BoundAugmented):
        for name, k in zip(source.extensions, source.values):
            ext = get_extension(name)
            if ext.regression:
                break
            twist = ext.apply(k, twist, wl, wr, t_s, rate)
    return twist


def _at(t_query: np.ndarray, t_ref: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Linear interpolation of the rows of ``values`` (L, ...) at ``t_query`` (ns)."""
    i = np.clip(np.searchsorted(t_ref, t_query, side='right') - 1, 0, len(t_ref) - 2)
    span = np.maximum(t_ref[i + 1] - t_ref[i], 1)
    f = np.clip((t_query - t_ref[i]) / span, 0.0, 1.0)
    shape = (-1,) + (1,) * (values.ndim - 1)
    return values[i] * (1.0 - f).reshape(shape) + values[i + 1] * f.reshape(shape)


def window_terms(drives: Sequence[Drive], samples: PoseSamples, source: TwistSource,
                 options: DiagnosisOptions, ranges: Sequence[float], window_s: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Return (target (N, 3), valid (N,), translational terms (N, T), yaw terms (N, T)).

    The target is the body-velocity residual, ground truth minus the source, both through the
    differentiator of half window ``window_s``; the terms are the library's (at ``ranges``) as
    that target sees them (module docstring). Rows are ``samples``' poses.
    """
    count = len(residual.TERMS)
    n = samples.t_ns.size
    target = np.zeros((n, 3))
    valid = np.zeros(n, dtype=bool)
    moving = np.zeros((n, count))
    turning = np.zeros((n, count))
    base = source.base if isinstance(source, BoundAugmented) else source
    shift = int(getattr(source, 'output_offset_ns', 0))
    for index in np.unique(samples.drive):
        rows = np.nonzero(samples.drive == index)[0]
        drive = drives[index]
        wheels = drive.wheels
        if len(wheels) < 2:
            continue
        t_ns = samples.t_ns[rows]
        if window_s == options.smoothing_s:   # what the samples hold
            truth, ok = samples.truth[rows], samples.valid[rows]
        else:
            t_truth, truth, ok = truth_velocities(drive, window_s)
            if not np.array_equal(t_truth, t_ns):
                continue  # not the poses the samples hold: left out
        poses = rollout_stream(source, wheels.t_ns, wheels.omega_l, wheels.omega_r,
                               max_dt_s=options.max_dt_s, interval=options.interval)
        at = t_ns.astype(np.int64) - shift
        model_poses = _at(at, wheels.t_ns, poses)
        model, ok_model = body_velocities(t_ns, model_poses, window_s)
        target[rows] = truth - model
        valid[rows] = ok & ok_model & integrated(t_ns, shift, wheels.t_ns, window_s,
                                                 options.max_dt_s)
        # the terms at every interval, held as the integrator holds them
        _, _, dt_s = stream_twists(base, wheels.t_ns, wheels.omega_l, wheels.omega_r,
                                   options.max_dt_s, options.interval)
        dt = dt_s[0]
        rate = base_rates(wheels, base, options.max_dt_s)
        t_s = (wheels.t_ns - wheels.t_ns[0]) * 1e-9
        twist = _incoming(source, wheels.omega_l, wheels.omega_r, t_s, rate)
        phi = residual.features(list(ranges), twist, rate) * dt[:, None]
        heading = poses[:, 2]
        cumulative = np.zeros((3, len(wheels), count))
        for c, weight in enumerate((np.ones_like(heading), np.cos(heading), np.sin(heading))):
            cumulative[c, 1:] = np.cumsum(phi[:-1] * weight[:-1, None], axis=0)
        at_poses = _at(at, wheels.t_ns, np.transpose(cumulative, (1, 0, 2)))  # (n, 3, T)
        window, slope, _ = difference_operator(t_ns, window_s)
        d = np.einsum('nw,nwct->nct', slope, at_poses[window])
        yaw = model_poses[:, 2]
        moving[rows] = np.cos(yaw)[:, None] * d[:, 1] + np.sin(yaw)[:, None] * d[:, 2]
        turning[rows] = d[:, 0]
    return target, valid, moving, turning
