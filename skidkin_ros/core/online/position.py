"""Online calibration from a reference's positions alone (GNSS without a heading).

Where the reference's heading is not measured (:mod:`skidkin_ros.core.online.heading`), each
learning segment compares the reference's positions with the wheels' path, the segment's start
pose taken from neither: the wheel path from the segment's start (the model's rollout of the
wheel steps, the reference frame's antenna at ``online.mount_x/y`` on the robot) is aligned on
the reference positions by a rigid motion (a heading and a translation per segment, weighted
least squares, Procrustes in closed form), and the residual is what the alignment leaves: the
positions the path's shape and length cannot match. Eliminating the nuisance (variable
projection, Kaufman's first-order Jacobian: the parameters' derivative projected off the
alignment's three directions) makes the residual depend on the parameters only through what
the positions observe: the path's length (speed scale) and its curvature against its length
(the yaw rate per metre). A straight segment says nothing about the yaw parameters, a turn on
the spot with the antenna on the axis nothing at all; the learner's observability rule (the
eigen-directions of the information, :meth:`WindowSolver._solve`, one home for it) keeps those
directions at their prior.

Each segment keeps at most ``MAX_POINTS`` of its reference positions (evenly spaced, the ends
always), each weighted by the reference's position noise (``online.sigma_xy``) plus the
model's noise over the path to it (its diagonal; the noise's correlation along the path is not
modelled). The residual has a fixed size (2 ``MAX_POINTS``, zero padded) so that a window of
segments is solved like the full-pose one.

What is not built on positions alone: change-of-ground detection and ground recognition (one
ground, forgetting by ``online.memory``), the learned reference noise and published-noise
scale (the file's stay), augmented models (their poses are not learned from). The residual is a
plain function of segments (:func:`position_residuals`): the offline calibrator could fit a
GNSS ground truth with it; it does not yet.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import math

import numpy as np

from skidkin_ros.core.calibration.segments import SegmentOptions
from skidkin_ros.core.kinematics.models import KinematicModel, MODELS
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.noise import NoiseModel
from skidkin_ros.core.odometry.reference import ReferenceStatus
from skidkin_ros.core.online.gates import _Ref, JUMP_CONFIRM
from skidkin_ros.core.timeunits import NS_PER_S

__all__ = ['PositionSegment', 'PositionLearner', 'position_residuals', 'MAX_POINTS']

# Reference positions kept per segment (evenly spaced; the residual's size is twice this).
MAX_POINTS = 16
# Positions alone observe the yaw parameters through the path's curvature only: segments are
# this many times online.horizon (and horizon_rad) long, and a direction of the parameters is
# updated only when the window's information on it reaches this many times
# online.min_information (studied on two drives, checked on held-out ones: docs).
HORIZON_FACTOR = 3.0
INFORMATION_FACTOR = 25.0
# Relative step of the central differences of the rollout (in each parameter's scale).
DIFF_STEP = 1e-6


@dataclass
class PositionSegment:
    """One position-only segment: reference positions and the wheel steps between them.

    ``u`` (m, 2): the reference frame's positions (world); ``left``, ``right``, ``dt_s``: the
    wheel steps from the first position to the last; ``ends`` (m,): the number of steps up to
    each position (0 for the first).
    """

    u: np.ndarray
    left: np.ndarray
    right: np.ndarray
    dt_s: np.ndarray
    ends: np.ndarray
    path_m: float


def _rollout(model: KinematicModel, k: np.ndarray, geometry: Geometry, seg: PositionSegment,
             mount: tuple[float, float]) -> tuple[np.ndarray, tuple]:
    """Return the antenna's positions (m, 2) in the segment's start frame, by the model.

    And the rollout itself (positions after each step, mid-step headings, step lengths and
    turns) for the noise's covariance.
    """
    v_x, v_y, omega = model.twist_components(k, geometry, seg.left, seg.right)
    dt = seg.dt_s
    turn = omega * dt
    heading = np.concatenate([[0.0], np.cumsum(turn)])
    mid = heading[:-1] + 0.5 * turn   # the heading at mid-step
    c, s = np.cos(mid), np.sin(mid)
    x = np.concatenate([[0.0], np.cumsum((v_x * c - v_y * s) * dt)])
    y = np.concatenate([[0.0], np.cumsum((v_x * s + v_y * c) * dt)])
    at = seg.ends
    ch, sh = np.cos(heading[at]), np.sin(heading[at])
    q = np.stack([x[at] + ch * mount[0] - sh * mount[1],
                  y[at] + sh * mount[0] + ch * mount[1]], axis=1)
    return q, (x, y, c, s, np.abs(v_x) * dt, turn)


def _path_covariance(q: np.ndarray, seg: PositionSegment, rollout: tuple, noise: NoiseModel,
                     sigma_xy: float) -> np.ndarray:
    """Return the covariance (2m, 2m) of the antenna path's points and the reference's.

    The model's noise per step (its forward and lateral variances, rotated into the start frame,
    and its heading variance, which turns the rest of the path about that step's end), summed
    along the path: the points' errors are correlated as the odometry's are. Plus the
    reference's white position noise.
    """
    x, y, c, s, dist, turn = rollout
    var = np.array([noise.step_variances(d, r) for d, r in zip(dist.tolist(), turn.tolist())])
    m = len(q)
    steps = dist.size
    before = np.arange(steps)[None, :] < seg.ends[:, None]   # (m, S): step s before point i
    gain = np.zeros((2 * m, 3 * steps))
    gain[0::2, :steps] = before * c
    gain[0::2, steps:2 * steps] = before * -s
    gain[1::2, :steps] = before * s
    gain[1::2, steps:2 * steps] = before * c
    gain[0::2, 2 * steps:] = before * -(q[:, 1:2] - y[None, 1:])
    gain[1::2, 2 * steps:] = before * (q[:, 0:1] - x[None, 1:])
    weights = np.concatenate([var[:, 0], var[:, 1], var[:, 2]])
    return (gain * weights) @ gain.T + sigma_xy ** 2 * np.eye(2 * m)


def _align(q: np.ndarray, u: np.ndarray) -> tuple[float, np.ndarray]:
    """Return the rotation angle and translation that best map q onto u (least squares)."""
    q_mean, u_mean = q.mean(0), u.mean(0)
    qc, uc = q - q_mean, u - u_mean
    cross = float((qc[:, 0] * uc[:, 1] - qc[:, 1] * uc[:, 0]).sum())
    dot = float((qc[:, 0] * uc[:, 0] + qc[:, 1] * uc[:, 1]).sum())
    theta = math.atan2(cross, dot)
    c, s = math.cos(theta), math.sin(theta)
    rot = np.array([[c, -s], [s, c]])
    return theta, u_mean - rot @ q_mean


def position_residuals(model: KinematicModel, k: np.ndarray, geometry: Geometry,
                       segments: list[PositionSegment], mount: tuple[float, float],
                       scale: np.ndarray, noise: NoiseModel, sigma_xy: float
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Return the whitened residuals (N, 2 MAX_POINTS) and their sensitivities (N, 2M, p).

    Per segment: the model's antenna path aligned on the reference positions (a rigid motion,
    the nuisance), the residual u - aligned path whitened by the points' covariance
    (:func:`_path_covariance`); the sensitivity is the derivative of the aligned path with
    respect to the parameters (in units of ``scale``). Both are projected off the alignment's
    directions in the whitened space (variable projection: the nuisance re-estimated to first
    order under that covariance). Zero padded.
    """
    size = 2 * MAX_POINTS
    p = k.size
    errors = np.zeros((len(segments), size))
    sens = np.zeros((len(segments), size, p))
    for n, seg in enumerate(segments):
        m = len(seg.u)
        q, rollout = _rollout(model, k, geometry, seg, mount)
        theta, shift = _align(q, seg.u)
        c, s = math.cos(theta), math.sin(theta)
        rot = np.array([[c, -s], [s, c]])
        # everything in the segment's start frame, as aligned: the reference's frame and
        # place do not matter
        cov = _path_covariance(q, seg, rollout, noise, sigma_xy)
        chol = np.linalg.cholesky(cov + 1e-12 * np.eye(2 * m))
        residual = ((seg.u - shift) @ rot - q).ravel()
        # d(path)/dk by central differences of the rollout
        jac = np.empty((2 * m, p))
        for j in range(p):
            step = np.zeros(p)
            step[j] = DIFF_STEP * scale[j]
            plus = _rollout(model, k + step, geometry, seg, mount)[0]
            minus = _rollout(model, k - step, geometry, seg, mount)[0]
            jac[:, j] = ((plus - minus) / (2.0 * DIFF_STEP)).ravel()
        # the alignment's directions: translation x, y and rotation about the origin
        nuisance = np.zeros((m, 2, 3))
        nuisance[:, 0, 0] = nuisance[:, 1, 1] = 1.0
        nuisance[:, 0, 2], nuisance[:, 1, 2] = -q[:, 1], q[:, 0]
        nuisance_w = np.linalg.solve(chol, nuisance.reshape(2 * m, 3))
        jac_w = np.linalg.solve(chol, jac)
        e_w = np.linalg.solve(chol, residual)
        basis, _ = np.linalg.qr(nuisance_w)
        errors[n, :2 * m] = e_w - basis @ (basis.T @ e_w)
        sens[n, :2 * m] = jac_w - basis @ (basis.T @ jac_w)
    return errors, sens


class PositionLearner:
    """The position-only learning of :class:`OnlineCalibrator` (module docstring); a mixin."""

    _positions: list | None = None    # the segment in progress: [(t_ns, x, y, path_m)]
    _position_window: list | None = None   # [[PositionSegment, inverse weight, fade]]
    _position_jumps = 0
    _position_cut: SegmentOptions | None = None

    def position_learning(self) -> bool:
        """Return True when this learner learns from positions alone (online.position_only).

        Only a base model's parameters (an augmented model's poses are then not used).
        """
        return self.params.position_only and self.model.name in MODELS

    def _judge_position(self, t_ns: int, x: float, y: float) -> None:
        """Judge a position the wheels now cover (gap, wheel gap, jump, stall); learn."""
        points = self._positions
        last = points[-1] if points else None
        if last is None:
            self._start_positions(t_ns, x, y)
            return
        params = self.params
        if t_ns - last[0] > params.max_gap * NS_PER_S:
            self._count(ReferenceStatus.GAP, f'reference gap of {(t_ns - last[0]) * 1e-9:.2f} '
                        f's (max_gap {params.max_gap:g} s): segment dropped, restarting')
            self._start_positions(t_ns, x, y)
            return
        moved = self._steps.motion(last[0], t_ns)
        if moved is None:
            self._count(ReferenceStatus.WHEEL_GAP, 'the wheel data has a gap since the last '
                        'reference pose: segment dropped, restarting')
            self._start_positions(t_ns, x, y)
            return
        wheel_dist, wheel_rot = moved
        dist = math.hypot(x - last[1], y - last[2])
        if dist == 0.0:
            self._stall_m += wheel_dist
            if self._stall_m > params.stall:
                self._count(ReferenceStatus.STALL, f'reference frozen while the wheels '
                            f'travelled {self._stall_m:.2f} m: not used, segment dropped')
                self._positions = None
                return
        else:
            self._stall_m = 0.0
        # an antenna off the axis moves as the robot turns on the spot
        lever = math.hypot(params.mount_x, params.mount_y) * abs(wheel_rot)
        if params.disagrees(abs(dist - wheel_dist), wheel_dist, slack_m=lever):
            self._position_jumps += 1
            self._count(ReferenceStatus.JUMP, f'reference moved {dist:.2f} m where the wheels '
                        f'say {wheel_dist:.2f} m: refused')
            if self._position_jumps >= JUMP_CONFIRM:
                self._start_positions(t_ns, x, y)
            return
        self._position_jumps = 0
        points.append((t_ns, x, y, last[3] + dist))
        self.counters[ReferenceStatus.ACCEPTED.value] += 1
        self.travel_m += dist
        self._last_accepted_wheel_ns = t_ns
        first = points[0]
        turn = self._steps.motion(first[0], t_ns)
        if turn is not None and self._position_options().ends(first[3], points[-1][3], turn[1],
                                                              t_ns - first[0]):
            self._learn_positions(points, turn[1])
            self._start_positions(t_ns, x, y)

    def _position_options(self) -> SegmentOptions:
        options = self._position_cut
        if options is None:
            options = self._position_cut = dataclasses.replace(
                self.options, horizon_m=self.options.horizon_m * HORIZON_FACTOR,
                horizon_rad=self.options.horizon_rad * HORIZON_FACTOR)
        return options

    def _start_positions(self, t_ns: int, x: float, y: float) -> None:
        self._positions = [(t_ns, x, y, 0.0)]
        self._position_jumps = 0
        self._last_accepted_wheel_ns = t_ns
        self.counters[ReferenceStatus.ACCEPTED.value] += 1
        # the wheel steps from here on are kept (the calibrator trims before its segment start)
        self._refs.clear()
        self._seg_start = _Ref(t_ns, x, y, 0.0, 0.0)

    def _position_segment(self, points: list) -> PositionSegment | None:
        """Return the segment of these positions (at most MAX_POINTS of them), or None."""
        if len(points) > MAX_POINTS:
            pick = np.unique(np.round(np.linspace(0, len(points) - 1, MAX_POINTS)).astype(int))
            points = [points[i] for i in pick]
        lefts, rights, dts, ends = [], [], [], [0]
        count = 0
        for a, b in zip(points[:-1], points[1:]):
            steps = self._steps.speeds(a[0], b[0])
            if steps is None:
                return None
            left, right, dt_s = self._merge_blocks(*steps)
            lefts.append(left)
            rights.append(right)
            dts.append(dt_s)
            count += dt_s.size
            ends.append(count)
        dt_all = np.concatenate(dts)
        if dt_all.size == 0 or dt_all.max() > self.options.max_gap_s:
            return None
        return PositionSegment(np.array([[p[1], p[2]] for p in points]), np.concatenate(lefts),
                               np.concatenate(rights), dt_all, np.array(ends),
                               float(points[-1][3] - points[0][3]))

    def _learn_positions(self, points: list, turn: float) -> None:
        """Learn one position-only segment: the window's step in the observable directions."""
        path = points[-1][3] - points[0][3]
        if len(points) < 3 or self.options.too_still(path, turn):
            self.counters['online_still'] += 1
            return
        seg = self._position_segment(points)
        if seg is None:
            self.counters['online_wheel_gap'] += 1
            return
        ground = self.active
        mount = (self.params.mount_x, self.params.mount_y)
        q = _rollout(self.model, ground.k, self.geometry, seg, mount)[0]
        theta, shift = _align(q, seg.u)
        c, s = math.cos(theta), math.sin(theta)
        miss = float(np.hypot(*(((seg.u - shift) @ np.array([[c, -s], [s, c]])) - q).T).max())
        if self.params.disagrees(miss, path):   # the full-pose learner's rule
            self.counters['online_inconsistent'] += 1
            self._warn('online_inconsistent', f"a {path:.2f} m segment's positions miss the "
                       f"wheels' path by {miss:.2f} m however placed: beyond any ground "
                       '(max_jump; online.mount_x/y wrong?); not learned')
            return
        if self._position_window is None:
            # no change of ground is detected on positions alone: the ground learned on them
            # starts from the parameters in force with the broad prior (online.prior_sigma), not
            # the file's covariance, which would hold it on the calibration ground for good
            ground.prior = self.prior_info.copy()
            ground.anchor = ground.k.copy()
        fade = math.exp(-path / self.params.memory)
        window = self._position_window or []
        for item in window:
            item[2] *= fade
        window.append([seg, np.eye(2 * MAX_POINTS), 1.0])
        window = [item for item in window[-int(self.params.window):] if item[2] > 1e-3]
        self._position_window = window
        self.counters['online_position_segments'] += 1
        ground.segments += 1
        ground.learned_m += path
        errors, sens = position_residuals(self.model, ground.k, self.geometry,
                                          [item[0] for item in window], mount, self.scale,
                                          self.noise, self.params.sigma_xy)
        self._solve(ground, window, errors, sens,
                    INFORMATION_FACTOR * self.params.min_information)
