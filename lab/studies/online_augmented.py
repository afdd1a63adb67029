"""Online calibration of an augmented model: online+augmented, online+plain, fixed augmented.

Simulated drives (``edd_asymmetric`` truth with a forward slip that grows with speed,
``speed_slip`` of ``SPEED_SLIP`` s/m, which the augmented model ``edd_asymmetric + speed_slip``
covers and the plain model cannot), 20 Hz wheels with encoder noise, a 10 Hz reference (the
truth plus white noise, as in :mod:`lab.studies.online`); from half the drive on, a new ground:
the forward speed loses ``SLIP`` and the yaw rate ``YAW_SLIP`` more (``terrain_regime`` mode
time). Four odometries on the same wheel samples:

* **fixed augmented**: the augmented model with the calibration ground's true values (the best a
  fixed file of that model can be: a conservative baseline for online);
* **online plain**: ``edd_asymmetric`` learning online from the same start;
* **online augmented**: the augmented model learning online (base and speed_slip.k);
* **true**: the augmented model with the true values of the ground under the robot (the floor).

Scores: ε_t and ε_θ over the whole drive (mean increment error over 2 m of true path,
:func:`skidkin_ros.sim.accuracy.increment_errors`). Run::

    python -m lab.bench.online_augmented_study [--seeds 1 2 11 12 13 14] [--effect ratio_yaw_slip]

``--effect ratio_yaw_slip``: the truth loses up to 40 % of its yaw rate at a slow/fast wheel
speed ratio near 0.5 instead (the model edd_asymmetric + ratio_yaw_slip).

``--effect residual_model``: the truth of the speed_slip case, modelled by a residual-model file
instead of the named extension: one coefficient (the term v|v| of the forward speed) that
reproduces the calibration ground's slip exactly (``residual_file``; level 2, input ranges
+-3 m/s and +-3 rad/s, fixed before any drive was run), the gains 1. On the new ground the slip
relative to the base twist is 1 / (1 - SLIP) times stronger: the residual effect changes
strength mid-drive, and online learning of the residual model's gains (its coefficients held)
should take gain_vx to 1 / (1 - SLIP) = 1.333. "fixed augmented" is then that file as it is.

``--effect residual_rate``: the same plus the simulator's lag of the forward speed while the
wheels speed up (``acceleration_slip``, tau ``ACCEL_TAU``), and in the file a rate term (level 3)
for it (-tau dv while speeding up, its first-order reading). The new ground makes the slip term
1.333x stronger but leaves the rate term as it was: one gain_vx cannot follow both (what a
gains-only residual model online can and cannot do). The floor adds acceleration_slip with tau
(approximate: the lag is not exactly a loss of tau dv).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from lab.studies.online import _reference, _scores, ground_poses, true_grounds
import numpy as np

from skidkin_ros.core.kinematics.augmented import AugmentedModel
from skidkin_ros.core.kinematics.extensions import get_extension
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.online import online_odometer
from skidkin_ros.sim.effects import make_effect
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate, Simulation

__all__ = ['ODOMETRIES', 'AugmentedResult', 'run_seed', 'table']

SPEED_SLIP = 0.25
SLIP, YAW_SLIP = 0.25, 0.15
# The effect on the truth and the extension that covers it: (strength, the extension's k on the
# new ground). speed_slip: v = (1 - SLIP) v0 (1 - k |v0|) = v1 (1 - k / (1 - SLIP) |v1|);
# ratio_yaw_slip (the simulator's peak 0.5 and width 0.15 are the extension's defaults):
# omega = (1 - YAW_SLIP) omega0 (1 - k bump) = omega1 (1 - k bump), the same k.
EFFECTS = {'speed_slip': (SPEED_SLIP, SPEED_SLIP / (1.0 - SLIP)),
           'ratio_yaw_slip': (0.4, 0.4),
           # the truth's speed slip, as the residual model's gain_vx (1 on the calibration ground)
           'residual_model': (1.0, 1.0 / (1.0 - SLIP)),
           # the same with a rate term: the slip term wants 1 / (1 - SLIP), the rate term 1
           'residual_rate': (1.0, 1.0 / (1.0 - SLIP))}
# The simulator's lag while speeding up (s) in the residual_rate drives.
ACCEL_TAU = 0.1
# The truth's effects (simulator effect, strength) besides the change of ground.
TRUTH = {'speed_slip': (('speed_slip', SPEED_SLIP),),
         'ratio_yaw_slip': (('ratio_yaw_slip', 0.4),),
         'residual_model': (('speed_slip', SPEED_SLIP),),
         'residual_rate': (('speed_slip', SPEED_SLIP), ('acceleration_slip', ACCEL_TAU))}
# The floor ('true'): named extensions and their values on the calibration and the new ground.
# acceleration_slip (v_x loses tau dv/dt while speeding up) is the first-order reading of the
# simulator's lag while speeding up: for residual_rate the floor is approximate.
FLOOR = {'speed_slip': (('speed_slip',), {'k': EFFECTS['speed_slip']}),
         'ratio_yaw_slip': (('ratio_yaw_slip',), {'k': EFFECTS['ratio_yaw_slip']}),
         'residual_model': (('speed_slip',), {'k': EFFECTS['speed_slip']}),
         'residual_rate': (('speed_slip', 'acceleration_slip'),
                           {'k': EFFECTS['speed_slip'], 'tau_s': (ACCEL_TAU, ACCEL_TAU)})}
# The learned value shown in the table.
LEARNED = {'speed_slip': 'speed_slip.k', 'ratio_yaw_slip': 'ratio_yaw_slip.k',
           'residual_model': 'residual_model.gain_vx', 'residual_rate': 'residual_model.gain_vx'}
# Input ranges of the residual-model file (m/s, rad/s, m/s^2, rad/s^2).
RESIDUAL_RANGE = 3.0


def residual_file(k: float = SPEED_SLIP, tau: float = 0.0) -> dict[str, float]:
    """Return a residual model equal to speed_slip k (and acceleration_slip tau) in its range.

    The correction of v_x is C p|p| with p = v / RESIDUAL_RANGE (clamped, scaled), so C = -k
    RESIDUAL_RANGE^2 gives -k v|v|, speed_slip's change, wherever k |v| stays below its cap.
    With tau > 0 (level 3): plus C' a on speeding up, a = dv / RESIDUAL_RANGE, C' = -tau
    RESIDUAL_RANGE: -tau dv, acceleration_slip's change.
    """
    values = {f'{name}_{side}': sign * RESIDUAL_RANGE for name in ('v', 'w', 'dv', 'dw')
              for side, sign in (('lo', -1.0), ('hi', 1.0))}
    values.update({'level': 2.0, 'vx_v_abs_v': -k * RESIDUAL_RANGE ** 2})
    if tau > 0.0:
        values.update({'level': 3.0, 'vx_dv_up': -tau * RESIDUAL_RANGE})
    return values


MODEL = 'edd_asymmetric'
ODOMETRIES = ('fixed augmented', 'online plain', 'online augmented', 'true')


def _flat(model: str, online: bool, effect: str = 'speed_slip') -> dict:
    values = DEFAULT_TRUE_PARAMS
    flat = {'model': model, 'robot': 'sim', f'models.{MODEL}.noise.calibrated': True,
            **{f'models.{MODEL}.{name}': v for name, v in values.items()},
            'online.enabled': online}
    if model == 'augmented' and effect.startswith('residual'):
        tau = ACCEL_TAU if effect == 'residual_rate' else 0.0
        flat.update({'augmented.base': MODEL, 'augmented.extensions': 'residual_model',
                     **{f'augmented.residual_model.{name}': value
                        for name, value in residual_file(tau=tau).items()}})
    elif model == 'augmented':
        flat.update({'augmented.base': MODEL, 'augmented.extensions': effect,
                     f'augmented.{effect}.k': EFFECTS[effect][0]})
    return flat


def _new_ground(effect: str = 'speed_slip') -> tuple[dict, float]:
    """Return the new ground's true base values and the extension's k (module docstring)."""
    return true_grounds()[1], EFFECTS[effect][1]


def _true_poses(sim: Simulation, interval: str, effect: str) -> np.ndarray:
    geometry = sim.config.geometry
    extensions, values = FLOOR[effect]
    structure = AugmentedModel(MODEL, extensions)
    new_values, _ = _new_ground(effect)
    sources = []
    for ground, base in enumerate((DEFAULT_TRUE_PARAMS, new_values)):
        named = {name: value[ground] for name, value in values.items()}
        sources.append(structure.bind(get_model(MODEL).bind(base, geometry), {
            ext: {name: v for name, v in named.items()
                  if name in get_extension(ext).param_names} for ext in extensions}))
    return ground_poses(sim, sources, interval)


@dataclass
class AugmentedResult:
    """One drive: ε_t and ε_θ per odometry, the learned values, the drive's length."""

    seed: int
    effect: str
    eps_t: dict
    eps_th: dict
    learned: dict
    length_m: float


def run_seed(seed: int, duration_s: float = 200.0, effect: str = 'speed_slip'
             ) -> AugmentedResult:
    """Run the four odometries on one drive (module docstring)."""
    effects = tuple(make_effect(name, strength) for name, strength in TRUTH[effect]) + (
        make_effect('terrain_regime', SLIP, mode='time', switch_frac=0.5, yaw=YAW_SLIP),)
    sim = simulate(SimConfig(duration_s=duration_s, seed=seed, effects=effects))
    reference = _reference(sim, np.random.default_rng(seed))
    poses = {}
    learned = {}
    for name, model, online in (('fixed augmented', 'augmented', False),
                                ('online plain', MODEL, True),
                                ('online augmented', 'augmented', True)):
        config = OdometryConfig.from_flat(_flat(model, online, effect))
        odometer = online_odometer(config)
        poses[name] = odometer.predict(sim.wheels, reference=reference if online else None).poses
        if online:
            learned[name] = odometer.learner.values
    poses['true'] = _true_poses(sim, config['interval'], effect)
    scores = {name: _scores(sim, p) for name, p in poses.items()}
    return AugmentedResult(seed, effect, {k: float(v[0].mean()) for k, v in scores.items()},
                           {k: float(v[1].mean()) for k, v in scores.items()}, learned,
                           float(sim.truth.path_length()[-1]))


def table(results: Sequence[AugmentedResult]) -> str:
    """Return the study's table: ε_t (mm/m... as metres per 2 m) and ε_θ per odometry."""
    head = ('| effect | seed | path m | ' + ' | '.join(f'ε_t {n}' for n in ODOMETRIES)
            + ' | online aug / online plain | online aug / fixed aug | ε_θ online aug / plain |'
              ' learned k or gain (true new ground) |')
    lines = [head, '|' + '---|' * (head.count('|') - 1)]
    for r in results:
        e = r.eps_t
        _, new_k = _new_ground(r.effect)
        lines.append(
            f'| {r.effect} | {r.seed} | {r.length_m:.0f} | '
            + ' | '.join(f'{e[n]:.4f}' for n in ODOMETRIES)
            + f' | {e["online augmented"] / e["online plain"]:.2f}'
            f' | {e["online augmented"] / e["fixed augmented"]:.2f}'
            f' | {r.eps_th["online augmented"] / r.eps_th["online plain"]:.2f}'
            f' | {r.learned["online augmented"][LEARNED[r.effect]]:.3f} ({new_k:.3f}) |')
    return '\n'.join(lines)
