"""Per-pose body-velocity residuals: ground truth minus model, and the signals they are traced on.

1. **Fresh poses only.** Sample-and-held ground-truth poses (ICP at 10 Hz held onto 20 Hz rows)
   are dropped (:func:`skidkin_ros.core.drive.fresh_pose_mask`): a held pose is not a measurement.
2. **Differentiate.** At each fresh pose a local quadratic is fitted to x, y and yaw over the
   poses within +-``smoothing_s`` and differentiated there; the world velocity is rotated into
   the body frame with the fitted heading (:func:`body_velocities`). Noisy 10 Hz ICP poses give
   usable velocities this way, where finite differences would not.
3. **Model alike.** The model runs over the whole drive through the shared integrator, its
   poses are read at the same stamps (shifted by a time offset) and go through the same
   differentiator, so both sides are smoothed alike and the residual is the model's error, not
   the smoother's.
4. **Signals.** At each pose: the held wheel speeds, their sum, difference, ratio and time
   derivatives, the base model's body speed and yaw rate and their rates as the integrator has
   them (backward differences over one wheel sample; the speeding-up part of the forward one),
   curvature, v omega, direction, time in the drive, position, the IMU yaw rate, and one signal
   of the drive's history, ``reversal_speed`` (each wheel's speed weighted by how recently it
   reversed: what a drivetrain's backlash follows, :func:`reversal_speed`): what
   :mod:`.tracing` correlates with the residuals.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from skidkin_ros.core.calibration.diagnosis.options import DiagnosisOptions
from skidkin_ros.core.drive import Drive, fresh_pose_mask, WheelSamples
from skidkin_ros.core.kinematics.augmented import twist_rates
from skidkin_ros.core.kinematics.extensions import speeding_up
from skidkin_ros.core.kinematics.models import BoundModel
from skidkin_ros.core.odometry.integrator import rollout_stream
from skidkin_ros.core.timeunits import s_to_ns
from skidkin_ros.errors import DataError

__all__ = ['COMPONENTS', 'PoseSamples', 'body_velocities', 'difference_operator', 'integrated',
           'truth_velocities', 'pose_samples',
           'model_rollouts', 'pose_residuals', 'reversal_speed', 'REVERSAL_SPAN_RAD']

COMPONENTS = ('v_x', 'v_y', 'omega')
# The rotation after a reversal over which reversal_speed's weight falls from 1 to 0 (rad): the
# plays of drivetrains are tenths of a radian; a wider window also follows the acceleration
# that comes after most reversals (an acceleration slip's residual followed it more than
# speeding_up at 1 rad).
REVERSAL_SPAN_RAD = 0.5


def reversal_speed(omega: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """Return omega max(1 - theta / REVERSAL_SPAN_RAD, 0), theta the rotation since it reversed.

    theta: the wheel's rotation (rad, |omega| dt summed) since its direction last changed (a
    standstill does not end a direction); from the drive start before any reversal. A
    backlash loses the motion of the first part of a turn after each reversal: the residual
    it leaves follows this signal, which no function of the present speeds is.
    """
    omega = np.asarray(omega, dtype=float)
    if omega.size < 2:
        return np.zeros(omega.shape)
    dt = np.diff(np.asarray(t_s, dtype=float), prepend=t_s[0])
    sign = np.sign(omega)
    moving = sign != 0
    # the direction held through standstills (forward fill of the last non-zero sign)
    last = np.maximum.accumulate(np.where(moving, np.arange(sign.size), 0))
    held = sign[last]
    changed = np.zeros(sign.size, bool)
    changed[1:] = (held[1:] != held[:-1]) & (held[:-1] != 0)
    turned = np.cumsum(np.abs(omega) * dt)
    start = np.maximum.accumulate(np.where(changed, np.arange(sign.size), 0))
    theta = turned - turned[start]
    return omega * np.maximum(1.0 - theta / REVERSAL_SPAN_RAD, 0.0)


# The differentiator's operator depends on the stamps only: the lag scan and every candidate run
# the model at the same stamps, so it is computed once per set of stamps (a few kept).
_OPERATORS: dict[tuple[int, int, bytes], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
_OPERATORS_KEPT = 64


def _operator(t_ns: np.ndarray, half_window_s: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (index (n, w), operator (n, 3, w), valid (n,)): coef = operator @ values[index]."""
    key = (len(t_ns), s_to_ns(half_window_s),
           np.ascontiguousarray(t_ns, dtype=np.int64).tobytes())
    cached = _OPERATORS.get(key)
    if cached is not None:
        return cached
    t_s = (np.asarray(t_ns, dtype=np.int64) - int(t_ns[0])) * 1e-9
    n = t_s.size
    lo = np.searchsorted(t_s, t_s - half_window_s, side='left')
    hi = np.searchsorted(t_s, t_s + half_window_s, side='right')
    width = int((hi - lo).max())
    offsets = np.arange(width)
    index = lo[:, None] + offsets[None, :]
    inside = index < hi[:, None]
    index = np.minimum(index, n - 1)
    tau = np.where(inside, t_s[index] - t_s[:, None], 0.0)
    weight = inside.astype(float)
    basis = np.stack([np.ones_like(tau), tau, tau * tau], axis=-1) * weight[..., None]
    normal = np.einsum('nwi,nwj->nij', basis, basis)
    left = (tau < 0) & inside
    right = (tau > 0) & inside
    valid = (inside.sum(axis=1) >= 4) & left.any(axis=1) & right.any(axis=1)
    normal[~valid] = np.eye(3)
    operator = np.linalg.solve(normal, np.transpose(basis, (0, 2, 1)))  # (n, 3, w)
    if len(_OPERATORS) >= _OPERATORS_KEPT:
        _OPERATORS.clear()
    _OPERATORS[key] = (index, operator, valid)
    return index, operator, valid


def difference_operator(t_ns: np.ndarray, half_window_s: float
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (index (n, w), slope weights (n, w), valid (n,)) of :func:`body_velocities`."""
    index, operator, valid = _operator(t_ns, half_window_s)
    return index, operator[:, 1], valid


def body_velocities(t_ns: np.ndarray, poses: np.ndarray, half_window_s: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Differentiate poses (N, 3) by local quadratic fits; return body twists (N, 3) and valid.

    Each pose's window holds the poses within +-half_window_s; at least 4 are needed (and one on
    each side) for a valid estimate. World velocities are rotated into the body frame with the
    fitted heading.
    """
    n = len(t_ns)
    out = np.zeros((n, 3))
    if n < 4:
        return out, np.zeros(n, dtype=bool)
    index, operator, valid = _operator(t_ns, half_window_s)
    values = poses[index]  # (n, w, 3)
    # the fitted slopes of the three coordinates and the fitted heading: the entries of
    # operator @ values that are used (the whole (n, 3, 3) product costs several times more)
    slope = np.einsum('nw,nwc->nc', operator[:, 1], values)
    vx_w, vy_w, omega = slope[:, 0], slope[:, 1], slope[:, 2]
    yaw = np.einsum('nw,nw->n', operator[:, 0], values[:, :, 2])
    cos_y, sin_y = np.cos(yaw), np.sin(yaw)
    out[:, 0] = cos_y * vx_w + sin_y * vy_w
    out[:, 1] = -sin_y * vx_w + cos_y * vy_w
    out[:, 2] = omega
    return out, valid.copy()


def truth_velocities(drive: Drive, half_window_s: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (fresh ground-truth stamps, body twists (N, 3), valid) of one drive."""
    truth = drive.truth
    fresh = fresh_pose_mask(truth.x, truth.y, truth.yaw) & truth.valid
    t_ns = truth.t_ns[fresh]
    twist, valid = body_velocities(t_ns, truth.poses[fresh], half_window_s)
    return t_ns, twist, valid


def integrated(t_ns: np.ndarray, shift: int, t_wheels: np.ndarray, window_s: float,
               max_dt_s: float) -> np.ndarray:
    """Tell, per pose, whether the model is integrated over its whole window.

    A window whose poses reach past the wheels' first or last stamp (the recording's, before
    the source's time offset moves the model), or whose model poses (at the stamps less the
    offset) span a step longer than ``max_dt_s`` (a gap the integrator does not cross), holds
    poses where the model stands still while the ground truth moves: its target is not the
    model's error, and its terms (integrated over the wheel steps) do not see that stretch.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    half = s_to_ns(window_s)
    first = t_ns[np.searchsorted(t_ns, t_ns - half, side='left')]    # the window's poses' ends
    last = t_ns[np.searchsorted(t_ns, t_ns + half, side='right') - 1]
    gaps = np.zeros(len(t_wheels), dtype=np.int64)   # gaps among the steps before each sample
    gaps[1:] = np.cumsum(np.diff(t_wheels) * 1e-9 > max_dt_s)
    k0 = np.clip(np.searchsorted(t_wheels, first - shift, side='right') - 1, 0,
                 len(t_wheels) - 1)
    k1 = np.clip(np.searchsorted(t_wheels, last - shift, side='left'), 0, len(t_wheels) - 1)
    return (first >= t_wheels[0]) & (last <= t_wheels[-1]) & (gaps[k1] == gaps[k0])


def _model_velocities(source: Any, drive: Drive, t_ns: np.ndarray,
                      half_window_s: float, max_dt_s: float, interval: str,
                      poses: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Model body twists at the stamps, through the same differentiator as the ground truth.

    ``poses``: the source's rollout over the drive's wheel samples, when the caller has it
    (:func:`model_rollouts`).
    """
    wheels = drive.wheels
    if poses is None:
        poses = rollout_stream(source, wheels.t_ns, wheels.omega_l, wheels.omega_r,
                               max_dt_s=max_dt_s, interval=interval)
    shift = int(getattr(source, 'output_offset_ns', 0))
    at = np.asarray(t_ns, dtype=np.int64) - shift
    ref = wheels.t_ns
    model_poses = np.stack([np.interp(at, ref, poses[:, i]) for i in range(3)], axis=-1)
    model, valid = body_velocities(t_ns, model_poses, half_window_s)
    return model, valid & integrated(t_ns, shift, ref, half_window_s, max_dt_s)


@dataclass(frozen=True)
class PoseSamples:
    """Fresh ground-truth poses of all drives, with their velocities and signals.

    ``drive``: index of each pose's drive; ``truth``: ground-truth body twists (N, 3);
    ``signals``: {name: (N,)}; ``base_twist``: the base model's twist of the held wheel speeds;
    ``base_rate``: its rate of change at the held sample (as the augmented model has it).
    """

    drive: np.ndarray
    t_ns: np.ndarray
    truth: np.ndarray
    valid: np.ndarray
    signals: dict[str, np.ndarray]
    base_twist: np.ndarray
    base_rate: np.ndarray


def _held_index(wheels: WheelSamples, t_ns: np.ndarray) -> np.ndarray:
    return np.clip(np.searchsorted(wheels.t_ns, t_ns, side='right') - 1, 0, len(wheels) - 1)


def base_rates(wheels: WheelSamples, base: BoundModel, max_dt_s: float) -> np.ndarray:
    """Return the base twist's rate at every wheel sample (L, 3), as the integrator has it."""
    twist = np.asarray(base.twist(wheels.omega_l, wheels.omega_r), dtype=float)[None]
    dt_s = np.zeros((1, len(wheels)))
    dt_s[0, :-1] = np.diff(wheels.t_ns) * 1e-9
    restart = np.zeros(dt_s.shape, dtype=bool)
    restart[:, 1:] = dt_s[:, :-1] > max_dt_s
    dt_s[dt_s > max_dt_s] = 0.0
    return twist_rates(twist, dt_s, restart)[0]


def _speed_rate(omega: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """Return d(omega)/dt at every sample: one derivative per distinct stamp.

    A stamp repeated by the publisher (dt = 0) made np.gradient divide by zero, and its inf/NaN
    reached the traced signals; the samples of a repeated stamp share the derivative of the last
    of them. Without repeated stamps this is np.gradient, bit for bit.
    """
    stamps, inverse = np.unique(t_s, return_inverse=True)
    if len(stamps) <= 2:
        return np.zeros(len(omega))
    if len(stamps) == len(t_s):
        return np.gradient(omega, t_s)
    last = np.zeros(len(stamps), dtype=int)
    last[inverse] = np.arange(len(t_s))   # the last sample of each stamp
    return np.gradient(np.asarray(omega)[last], stamps)[inverse]


def _signals(drive: Drive, t_ns: np.ndarray, base: BoundModel, max_dt_s: float
             ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """Return the signals at the stamps (step 4 of the module docstring), base twist, rate."""
    wheels = drive.wheels
    index = _held_index(wheels, t_ns)
    wl, wr = wheels.omega_l[index], wheels.omega_r[index]
    rate = base_rates(wheels, base, max_dt_s)[index]
    t_w = wheels.t_s
    dwl = np.interp(t_ns, wheels.t_ns, _speed_rate(wheels.omega_l, t_w))
    dwr = np.interp(t_ns, wheels.t_ns, _speed_rate(wheels.omega_r, t_w))
    model_twist = base.twist(wl, wr)
    v, w = model_twist[:, 0], model_twist[:, 2]
    big = np.maximum(np.abs(wl), np.abs(wr))
    small = np.minimum(np.abs(wl), np.abs(wr))
    ratio = np.where((wl * wr > 0) & (big > 0), small / np.where(big > 0, big, 1), -1.0)
    poses = drive.truth.interpolate(t_ns)
    named = {
        'omega_l': wl, 'omega_r': wr, 'wheel_sum': wl + wr, 'wheel_diff': wr - wl,
        'wheel_ratio': ratio, 'd_omega_l': dwl, 'd_omega_r': dwr,
        'd_wheel_sum': dwl + dwr, 'd_wheel_diff': dwr - dwl,
        'body_speed': v, 'yaw_rate': w, 'd_body_speed': rate[:, 0], 'd_yaw_rate': rate[:, 2],
        'speeding_up': speeding_up(v, rate[:, 0]),
        'curvature': np.clip(w / np.where(np.abs(v) > 0.05, v, np.nan), -20, 20),
        'v_omega': v * w, 'v_abs_v': v * np.abs(v), 'direction': np.sign(v),
        'time_in_drive': (t_ns - wheels.t_ns[0]) * 1e-9,
        'x': poses[:, 0], 'y': poses[:, 1],
        # the world heading, times the speed: what a slope does (not a function of the wheels)
        'speed_sin_heading': np.abs(v) * np.sin(poses[:, 2]),
        'speed_cos_heading': np.abs(v) * np.cos(poses[:, 2]),
        # the drive's history: the wheels' speeds just after they reversed (a backlash)
        'reversal_speed': 0.5 * (reversal_speed(wheels.omega_l, t_w)
                                 + reversal_speed(wheels.omega_r, t_w))[index],
    }
    imu = drive.imu
    if imu is not None and len(imu.t_ns) > 1:
        named['imu_yaw_rate'] = np.interp(t_ns, imu.t_ns, imu.yaw_rate)
    return named, model_twist, rate


def pose_samples(drives: Sequence[Drive], base: BoundModel,
                 options: DiagnosisOptions) -> PoseSamples:
    """Collect the fresh poses of every drive with ground truth, their twists and signals.

    A signal missing from one drive (the IMU) is left out for all. Raises DataError when no
    drive has at least 4 ground-truth poses.
    """
    parts = {key: [] for key in ('drive', 't', 'truth', 'valid', 'base', 'rate')}
    signals: dict[str, list[np.ndarray]] = {}
    for index, drive in enumerate(drives):
        if drive.truth is None or len(drive.truth) < 4 or len(drive.wheels) < 2:
            continue
        t_ns, twist, valid = truth_velocities(drive, options.smoothing_s)
        named, model_twist, rate = _signals(drive, t_ns, base, options.max_dt_s)
        for key, value in named.items():
            signals.setdefault(key, []).append(np.asarray(value, dtype=float))
        parts['drive'].append(np.full(t_ns.size, index))
        parts['t'].append(t_ns)
        parts['truth'].append(twist)
        parts['valid'].append(valid)
        parts['base'].append(model_twist)
        parts['rate'].append(rate)
    if not parts['t']:
        raise DataError('no drive has at least 4 ground-truth poses: nothing to diagnose')
    count = sum(p.size for p in parts['t'])
    merged = {}
    for key, values in signals.items():
        merged[key] = np.concatenate(values) if sum(v.size for v in values) == count else None
    merged = {k: v for k, v in merged.items() if v is not None}
    return PoseSamples(np.concatenate(parts['drive']), np.concatenate(parts['t']),
                       np.concatenate(parts['truth']), np.concatenate(parts['valid']),
                       merged, np.concatenate(parts['base']), np.concatenate(parts['rate']))


def model_rollouts(drives: Sequence[Drive], samples: PoseSamples, source: Any,
                   options: DiagnosisOptions) -> dict[int, np.ndarray]:
    """Return the source's poses at every wheel sample of each drive with fresh poses.

    What :func:`pose_residuals` reads the model's poses from. A time offset only moves the
    stamps they are read at, so sources that differ only by it share these (the lag scan).
    """
    return {int(index): rollout_stream(source, drives[index].wheels.t_ns,
                                       drives[index].wheels.omega_l,
                                       drives[index].wheels.omega_r,
                                       max_dt_s=options.max_dt_s, interval=options.interval)
            for index in np.unique(samples.drive)}


def pose_residuals(drives: Sequence[Drive], samples: PoseSamples, source: Any,
                   options: DiagnosisOptions, rollouts: dict[int, np.ndarray] | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Return (residual (N, 3) = truth - model body twist, valid (N,)) at the fresh poses.

    ``rollouts``: the source's :func:`model_rollouts` (equal to them, or to those of the
    source without its time offset), when the caller has them.
    """
    residual = np.zeros(samples.truth.shape)
    valid = samples.valid.copy()
    for index in np.unique(samples.drive):
        rows = samples.drive == index
        model, ok = _model_velocities(source, drives[index], samples.t_ns[rows],
                                      options.smoothing_s, options.max_dt_s, options.interval,
                                      None if rollouts is None else rollouts[int(index)])
        residual[rows] = samples.truth[rows] - model
        valid[rows] &= ok
    return residual, valid
