"""Undeclared-effect study: inject each simulator effect, diagnose blind, compare with the truth.

For every effect of ``skidkin_ros.sim.effects`` (and for effect-free data): simulate two training
and three evaluation drives of a robot whose true model is ``edd_symmetric`` plus that effect at a
seeded random strength, give them ICP-like ground truth (10 Hz, noisy, held onto the 20 Hz wheel
grid), calibrate ``edd_symmetric``, run :func:`skidkin_ros.core.calibration.diagnosis.diagnose`
without telling it the effect, and score on the evaluation drives: the base model, the augmented
one, and the simulator's true model driven by the same noisy wheel speeds.

The simulator reports each wheel's speed at its stamp, so the trapezoid between two samples
(``interval: midpoint``, what ``skidkin calibrate`` chooses on these drives) integrates them
without a time offset, and the diagnosis runs under it (:data:`SIM_INTERVAL`): it then needs no
stamp-convention row. Under ``starting`` the speeds lag by half a period, under ``ending`` they
lead by as much (:func:`convention_offset_s`).

``skidkin effects`` prints the table in the README (:func:`run_study` yields the rows one case at
a time; each :class:`EffectCase` gives its table row).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Iterator, Sequence

import numpy as np

from skidkin_ros.core.calibration.diagnosis import (diagnose, DiagnosisOptions, DiagnosisResult,
                                                    ModelState)
from skidkin_ros.core.calibration.evaluation import ErrorStats, relative_errors
from skidkin_ros.core.calibration.fitting import fit_model
from skidkin_ros.core.calibration.predictor import SegmentPredictor
from skidkin_ros.core.calibration.segments import cut_segments
from skidkin_ros.core.drive import Drive, PoseTrack
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.sim.effects import Effect, EFFECT_NAMES, EFFECTS, make_effect
from skidkin_ros.sim.simulate import SimConfig, simulate

__all__ = ['GEOMETRY', 'TRUE_PARAMS', 'STRENGTH_SEED', 'SIM_INTERVAL', 'TABLE_HEADER', 'icp_like',
           'sim_drives', 'convention_offset_s',
           'true_state', 'drawn_effect', 'EffectCase', 'run_case', 'run_study']

GEOMETRY = Geometry(0.1651, 0.555)
TRUE_PARAMS = {'alpha': 0.9, 'b_hat': 0.85}
WHEEL_PERIOD_S = 0.05
STRENGTH_SEED = 7
# The sample-interval convention that integrates the simulator's wheel speeds exactly.
SIM_INTERVAL = 'midpoint'


def convention_offset_s(interval: str) -> float:
    """Return the time offset (s) that makes the simulator's speeds right under ``interval``."""
    return {'starting': -0.5, 'midpoint': 0.0, 'ending': 0.5}[interval] * WHEEL_PERIOD_S


def icp_like(drive: Drive, rng: np.random.Generator, sigma_xy: float = 0.01,
             sigma_yaw: float = 0.003) -> Drive:
    """Return the drive with ICP-like truth: 10 Hz noisy poses held onto the 20 Hz wheel grid."""
    truth = drive.truth
    held = np.arange(len(truth)) // 2 * 2
    noise = rng.normal(0.0, 1.0, (3, len(truth)))
    return replace(drive, truth=PoseTrack(
        truth.t_ns, truth.x[held] + sigma_xy * noise[0][held],
        truth.y[held] + sigma_xy * noise[1][held], truth.yaw[held] + sigma_yaw * noise[2][held]))


def sim_drives(effect: Effect | None, seeds: Sequence[int], duration_s: float) -> list[Drive]:
    drives = []
    for seed in seeds:
        config = SimConfig(duration_s=duration_s, seed=seed, true_model='edd_symmetric',
                           true_params=TRUE_PARAMS, effects=(effect,) if effect else ())
        drives.append(icp_like(simulate(config).drive(f'sim{seed}'),
                               np.random.default_rng(100 + seed)))
    return drives


def true_state(effect: Effect | None, duration_s: float,
               interval: str = SIM_INTERVAL) -> ModelState:
    """Return the simulator's true model as an augmented model run under ``interval``."""
    centre = convention_offset_s(interval)
    extensions = {'time_offset': {'offset_s': centre}} if centre else {}
    if effect is not None:
        k = effect.strength
        extensions[effect.name] = {
            'time_offset': {'offset_s': k + centre}, 'first_order_lag': {'tau_s': k},
            'speed_slip': {'k': k}, 'ratio_yaw_slip': {'k': k}, 'lateral_skid': {'k': k},
            'direction_asymmetry': {'k': k},
            'terrain_regime': {'k': k, 'switch_s': 0.5 * duration_s}}[effect.name]
    return ModelState(tuple(extensions), dict(TRUE_PARAMS), extensions)


def drawn_effect(name: str) -> Effect:
    """Return the effect at a strength drawn uniformly in its range (seeded per effect)."""
    spec = EFFECTS[name]
    rng = np.random.default_rng([STRENGTH_SEED, EFFECT_NAMES.index(name)])
    return make_effect(name, float(rng.uniform(spec.low, spec.high)))


TABLE_HEADER = ('| injected | found | eps_t m/m: base -> augmented (true model) | '
                'eps_theta deg/m: base -> augmented (true model) |', '|---|---|---|---|')


@dataclass(frozen=True)
class EffectCase:
    """One row of the study: the diagnosis and the true model's errors on the same segments."""

    effect: Effect | None
    result: DiagnosisResult
    truth_t: ErrorStats
    truth_theta: ErrorStats

    def row(self) -> str:
        """Return the case's row of the README table (held-out medians, base -> augmented)."""
        first, last = self.result.steps[0], self.result.steps[-1]
        found = ', '.join(self.result.extensions) or 'nothing'
        effect = self.effect
        label = f'{effect.name} {effect.strength:.3g}' if effect else 'none'
        return (f'| {label} | {found} | {first.stats_t.median:.4f} -> '
                f'{last.stats_t.median:.4f} ({self.truth_t.median:.4f}) | '
                f'{first.stats_theta.median:.3f} -> {last.stats_theta.median:.3f} '
                f'({self.truth_theta.median:.3f}) |')


def run_case(effect: Effect | None, duration_s: float = 120.0,
             options: DiagnosisOptions | None = None) -> EffectCase:
    train = sim_drives(effect, [1, 2], duration_s)
    evaluate = sim_drives(effect, [3, 4, 5], duration_s)
    options = options or DiagnosisOptions(interval=SIM_INTERVAL)
    base = fit_model('edd_symmetric', GEOMETRY, cut_segments(train, options.train_segments()))
    result = diagnose(train, evaluate, GEOMETRY, {'edd_symmetric': base.values}, 'edd_symmetric',
                      options)
    predictor = SegmentPredictor(evaluate, cut_segments(evaluate, options.eval_segments()),
                                 interval=options.interval)
    errors = predictor.errors(true_state(effect, duration_s, options.interval).bind(
        'edd_symmetric', GEOMETRY))
    eps_t, eps_theta = relative_errors(errors, predictor.segments.path_m,
                                       options.min_eval_path_m)
    return EffectCase(effect, result, ErrorStats.of(eps_t), ErrorStats.of(eps_theta))


def run_study(names: Sequence[str | None] = (None,) + tuple(EFFECT_NAMES)
              ) -> Iterator[EffectCase]:
    """Run the cases in order (None: effect-free data), each effect at its drawn strength."""
    for name in names:
        yield run_case(drawn_effect(name) if name else None)
