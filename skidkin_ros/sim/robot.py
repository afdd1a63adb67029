"""Motion truth of the simulated skid-steer robot: commands, motor response, true poses.

The robot is driven over the (omega_l, omega_r) input space like the trajectories of Baril et
al. (2020): commanded wheel-speed pairs (straight forward and backward, arcs of both signs and
both directions, spins, random pairs), each held a few seconds. The command planner is closed
loop on the TRUE pose: before holding a command it predicts where the robot would end and, when
that leaves the arena disc, picks another command (finally one steering back to the centre), so
the lidar always sees the scene. The motors follow the commands through a first-order response.

The true body twist is a true kinematic model applied to the actual (noise-free) wheel speeds,
modified by the named effects of :mod:`skidkin_ros.sim.effects`; it is integrated on a fine grid
(1 kHz by default) with the project's one integrator
(:func:`skidkin_ros.core.odometry.integrator.rollout`).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Sequence

import numpy as np

from skidkin_ros.core.kinematics.models import BoundModel
from skidkin_ros.core.odometry.se2 import rollout, wrap_angle
from skidkin_ros.core.timeunits import s_to_ns
from skidkin_ros.sim.effects import apply_effects, Effect

__all__ = ['COMMAND_KINDS', 'CommandSchedule', 'TruthTrace', 'plan_commands', 'motor_response',
           'scripted_commands', 'true_motion']

COMMAND_KINDS: tuple[str, ...] = (
    'forward', 'backward', 'arc_forward_left', 'arc_forward_right', 'arc_backward_left',
    'arc_backward_right', 'spin_left', 'spin_right', 'random')
# Candidate commands tried per hold before falling back to steering home.
_CANDIDATES = 12
# Steps used to predict where a held command ends.
_PREDICTION_STEPS = 40


@dataclass(frozen=True)
class CommandSchedule:
    """Commanded wheel speeds (rad/s) held from each start time (ns) to the next."""

    t_ns: np.ndarray
    omega_l: np.ndarray
    omega_r: np.ndarray
    kind: tuple[str, ...]

    def __len__(self) -> int:
        return int(self.t_ns.size)

    def at(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the commands in force at the given stamps (zero-order hold)."""
        index = np.searchsorted(self.t_ns, np.asarray(t_ns), side='right') - 1
        index = np.clip(index, 0, len(self) - 1)
        return self.omega_l[index], self.omega_r[index]


@dataclass(frozen=True)
class TruthTrace:
    """The true motion on the fine grid: stamps, actual wheel speeds, body twist, poses."""

    t_ns: np.ndarray
    cmd_l: np.ndarray
    cmd_r: np.ndarray
    omega_l: np.ndarray
    omega_r: np.ndarray
    twist: np.ndarray
    poses: np.ndarray
    masks: dict


def motor_response(cmd: np.ndarray, dt_s: float, tau_s: float) -> np.ndarray:
    """Return the wheel speeds of motors following commands through 1 / (tau s + 1), from rest."""
    if tau_s <= 0.0:
        return np.asarray(cmd, dtype=float).copy()
    decay = math.exp(-dt_s / tau_s)
    from scipy.signal import lfilter  # scipy.signal: about 1 s of CPU to import

    return lfilter([0.0, 1.0 - decay], [1.0, -decay], np.asarray(cmd, dtype=float), axis=0)


def true_motion(schedule: CommandSchedule, t_ns: np.ndarray, true_model: BoundModel,
                effects: Sequence[Effect], motor_tau_s: float, duration_s: float,
                start_pose: Sequence[float] = (0.0, 0.0, 0.0)) -> TruthTrace:
    """Simulate the truth on the fine grid t_ns (uniform, starting at the drive start)."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    t_s = (t_ns - t_ns[0]) * 1e-9
    dt_s = float(t_s[1] - t_s[0]) if t_s.size > 1 else 1e-3
    cmd_l, cmd_r = schedule.at(t_ns)
    omega_l = motor_response(cmd_l, dt_s, motor_tau_s)
    omega_r = motor_response(cmd_r, dt_s, motor_tau_s)
    step_dt = np.full(t_s.size, dt_s)

    def integrate(twist: np.ndarray) -> np.ndarray:
        # Pose i is the pose AT t_i: the twist of step i acts over [t_i, t_i+1).
        return rollout(twist, step_dt, start_pose)[:-1]

    twist, masks = apply_effects(effects, t_s, omega_l, omega_r, true_model.twist, integrate,
                                 duration_s)
    return TruthTrace(t_ns, cmd_l, cmd_r, omega_l, omega_r, twist, integrate(twist), masks)


def _draw_command(kind: str, rng: np.random.Generator, max_speed: float) -> tuple[float, float]:
    speed = float(rng.uniform(0.3, 1.0)) * max_speed
    ratio = float(rng.uniform(-0.6, 0.9))  # slow side / fast side; < 0: counter-rotating
    if kind == 'forward':
        return speed, speed * float(rng.uniform(0.97, 1.03))
    if kind == 'backward':
        return -speed, -speed * float(rng.uniform(0.97, 1.03))
    if kind == 'arc_forward_left':
        return speed * ratio, speed
    if kind == 'arc_forward_right':
        return speed, speed * ratio
    if kind == 'arc_backward_left':
        return -speed * ratio, -speed
    if kind == 'arc_backward_right':
        return -speed, -speed * ratio
    if kind == 'spin_left':
        return -speed, speed
    if kind == 'spin_right':
        return speed, -speed
    return float(rng.uniform(-max_speed, max_speed)), float(rng.uniform(-max_speed, max_speed))


def _predict_end(model: BoundModel, pose: np.ndarray, cmd: tuple[float, float],
                 hold_s: float) -> np.ndarray:
    twist = np.broadcast_to(model.twist(cmd[0], cmd[1]), (_PREDICTION_STEPS, 3))
    path = rollout(twist, np.full(_PREDICTION_STEPS, hold_s / _PREDICTION_STEPS), pose)
    return path


def _homing_command(model: BoundModel, pose: np.ndarray, max_speed: float,
                    wheel_radius: float, track_width: float) -> tuple[float, float]:
    """Return a wheel-speed pair steering toward the arena centre."""
    bearing = math.atan2(-pose[1], -pose[0]) - pose[2]
    bearing = float(wrap_angle(bearing))
    omega = float(np.clip(1.5 * bearing, -1.2, 1.2))
    v = 0.6 * max_speed * wheel_radius * max(0.0, math.cos(bearing))
    left = (v - omega * track_width / 2.0) / wheel_radius
    right = (v + omega * track_width / 2.0) / wheel_radius
    scale = max(1.0, abs(left) / max_speed, abs(right) / max_speed)
    return left / scale, right / scale


def plan_commands(rng: np.random.Generator, start_ns: int, duration_s: float,
                  fine_t_ns: np.ndarray, true_model: BoundModel, effects: Sequence[Effect],
                  motor_tau_s: float, max_speed_rad_s: float, hold_range_s: tuple[float, float],
                  arena_radius_m: float, initial_rest_s: float,
                  start_pose: Sequence[float] = (0.0, 0.0, 0.0)) -> CommandSchedule:
    """Plan a command schedule covering the input space while staying in the arena disc.

    Kinds cycle through a shuffled list of :data:`COMMAND_KINDS` so every kind appears; each
    candidate is checked by predicting its held motion from the true pose at the hold start.
    """
    geometry = true_model.geometry
    times = [int(start_ns)]
    left, right, kinds = [0.0], [0.0], ['rest']
    t_ns = int(start_ns + s_to_ns(initial_rest_s))
    end_ns = int(start_ns + s_to_ns(duration_s))
    queue: list[str] = []
    while t_ns < end_ns:
        schedule = CommandSchedule(np.array(times, dtype=np.int64), np.array(left),
                                   np.array(right), tuple(kinds))
        upto = fine_t_ns[fine_t_ns <= t_ns]
        trace = true_motion(schedule, upto, true_model, effects, motor_tau_s, duration_s,
                            start_pose)
        pose = trace.poses[-1]
        hold_s = float(rng.uniform(*hold_range_s))
        chosen = None
        for _ in range(_CANDIDATES):
            if not queue:
                queue = list(rng.permutation(COMMAND_KINDS))
            kind = str(queue[0])
            cmd = _draw_command(kind, rng, max_speed_rad_s)
            path = _predict_end(true_model, pose, cmd, hold_s)
            if np.all(np.hypot(path[:, 0], path[:, 1]) < arena_radius_m):
                queue.pop(0)
                chosen = (kind, cmd)
                break
            queue.append(queue.pop(0))
        if chosen is None:
            chosen = ('home', _homing_command(true_model, pose, max_speed_rad_s,
                                              geometry.wheel_radius, geometry.track_width))
            hold_s = min(hold_s, 1.5)
        times.append(t_ns)
        left.append(chosen[1][0])
        right.append(chosen[1][1])
        kinds.append(chosen[0])
        t_ns += s_to_ns(hold_s)
    return CommandSchedule(np.array(times, dtype=np.int64), np.array(left), np.array(right),
                           tuple(kinds))


def scripted_commands(start_ns: int, initial_rest_s: float,
                      script: Sequence[tuple[float, float, float]]) -> CommandSchedule:
    """Return a schedule from (hold_s, omega_l, omega_r) triples after an initial rest."""
    times = [int(start_ns)]
    left, right, kinds = [0.0], [0.0], ['rest']
    t_ns = int(start_ns + s_to_ns(initial_rest_s))
    for hold_s, omega_l, omega_r in script:
        times.append(t_ns)
        left.append(float(omega_l))
        right.append(float(omega_r))
        kinds.append('script')
        t_ns += s_to_ns(hold_s)
    return CommandSchedule(np.array(times, dtype=np.int64), np.array(left), np.array(right),
                           tuple(kinds))
