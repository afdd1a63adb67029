"""Undeclared-effect study: inject each simulator effect, diagnose blind, compare with the truth.

For every effect of ``skidkin_ros.sim.effects``, for drives with two effects at once (``PAIRS``)
and for effect-free data: simulate two training and three evaluation drives of a robot whose true
model is ``edd_symmetric`` plus those effects, each at a seeded random strength, give them
ICP-like ground truth (10 Hz, noisy, held onto the 20 Hz wheel grid), calibrate
``edd_symmetric``, run :func:`skidkin_ros.core.calibration.diagnosis.diagnose` without telling it
the effects, and score on the evaluation drives: the base model, the augmented one, and the
simulator's true model driven by the same noisy wheel speeds. The true model is the augmented
model with the effect's own extension where the simulator's effect is exactly one
(:func:`true_state`); otherwise (acceleration slip: a body-level response, not the extension's
derivative term) it is the simulator's own effect pipeline run on the wheel samples
(:class:`SimulatorTruth`).

The simulator reports each wheel's speed at its stamp, so the trapezoid between two samples
(``interval: midpoint``, what ``skidkin calibrate`` chooses on these drives) integrates them
without a time offset, and the diagnosis runs under it (:data:`SIM_INTERVAL`): it then needs no
stamp-convention row. Under ``starting`` the speeds lag by half a period, under ``ending`` they
lead by as much (:func:`convention_offset_s`).

``python -m lab.cli effects`` prints the table of docs/results.md (:func:`run_study` yields
the rows one case at a time; each :class:`EffectCase` gives its table row). A case is named
``none``, an effect, or effects joined by ``+``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Iterator, Sequence

import numpy as np

from skidkin_ros.core.calibration.diagnosis import (diagnose, DiagnosisOptions, DiagnosisResult,
                                                    ModelState)
from skidkin_ros.core.calibration.evaluation import ErrorStats, relative_errors
from skidkin_ros.core.calibration.fitting import fit_model
from skidkin_ros.core.calibration.predictor import SegmentPredictor
from skidkin_ros.core.calibration.segments import cut_segments
from skidkin_ros.core.drive import Drive, PoseTrack
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.errors import ParameterError
from skidkin_ros.sim.effects import apply_effects, Effect, EFFECT_NAMES, EFFECTS, make_effect
from skidkin_ros.sim.simulate import SimConfig, simulate

__all__ = ['GEOMETRY', 'TRUE_PARAMS', 'STRENGTH_SEED', 'SIM_INTERVAL', 'TABLE_HEADER', 'PAIRS',
           'CASE_NAMES', 'icp_like', 'sim_drives', 'convention_offset_s', 'true_state',
           'SimulatorTruth', 'true_source', 'drawn_effect', 'case_effects', 'EffectCase',
           'run_case', 'run_study']

GEOMETRY = Geometry(0.1651, 0.555)
TRUE_PARAMS = {'alpha': 0.9, 'b_hat': 0.85}
WHEEL_PERIOD_S = 0.05
STRENGTH_SEED = 7
# The sample-interval convention that integrates the simulator's wheel speeds exactly.
SIM_INTERVAL = 'midpoint'
# Drives with two effects at once (the last row of the effects table in docs/results.md).
PAIRS: tuple[tuple[str, ...], ...] = (('acceleration_slip', 'lateral_skid'),)
CASE_NAMES: tuple[str, ...] = (('none',) + tuple(EFFECT_NAMES)
                               + tuple('+'.join(pair) for pair in PAIRS))
# The effects whose simulator form is exactly one extension (with its strength as parameter);
# a time offset is shifted by the convention's own offset (convention_offset_s) in true_state.
_EXACT = {
    'time_offset': lambda k, d: {'offset_s': k},
    'first_order_lag': lambda k, d: {'tau_s': k}, 'forward_lag': lambda k, d: {'tau_s': k},
    'yaw_lag': lambda k, d: {'tau_s': k}, 'speed_slip': lambda k, d: {'k': k},
    'ratio_yaw_slip': lambda k, d: {'k': k}, 'lateral_skid': lambda k, d: {'k': k},
    'direction_asymmetry': lambda k, d: {'k': k},
    'terrain_regime': lambda k, d: {'k': k, 'switch_s': 0.5 * d},
}


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


def _as_effects(effects: Effect | Sequence[Effect] | None) -> tuple[Effect, ...]:
    if effects is None:
        return ()
    return (effects,) if isinstance(effects, Effect) else tuple(effects)


def sim_drives(effects: Effect | Sequence[Effect] | None, seeds: Sequence[int],
               duration_s: float) -> list[Drive]:
    drives = []
    for seed in seeds:
        config = SimConfig(duration_s=duration_s, seed=seed, true_model='edd_symmetric',
                           true_params=TRUE_PARAMS, effects=_as_effects(effects))
        drives.append(icp_like(simulate(config).drive(f'sim{seed}'),
                               np.random.default_rng(100 + seed)))
    return drives


def true_state(effects: Effect | Sequence[Effect] | None, duration_s: float,
               interval: str = SIM_INTERVAL) -> ModelState:
    """Return the simulator's true model as an augmented model run under ``interval``.

    Only for effects that are exactly one extension (:func:`true_source` handles the others).
    """
    centre = convention_offset_s(interval)
    extensions = {'time_offset': {'offset_s': centre}} if centre else {}
    for effect in _as_effects(effects):
        params = _EXACT[effect.name](effect.strength, duration_s)
        if effect.name == 'time_offset':
            params['offset_s'] += centre
        extensions[effect.name] = params
    return ModelState(tuple(extensions), dict(TRUE_PARAMS), extensions)


@dataclass(frozen=True)
class SimulatorTruth:
    """The simulator's true model run on wheel samples: its effect pipeline, batch form only.

    A twist source for :class:`~skidkin_ros.core.calibration.predictor.SegmentPredictor` (which
    runs ``intervals``): the true kinematics and the effects of
    :func:`skidkin_ros.sim.effects.apply_effects` over each drive's held wheel speeds, published
    shifted by the convention's offset (:func:`convention_offset_s`, as in :func:`true_state`).
    """

    effects: tuple[Effect, ...]
    duration_s: float
    interval: str = SIM_INTERVAL
    stateful: bool = field(default=True, init=False)

    @property
    def output_offset_ns(self) -> int:
        """Shift of the published poses: the convention's offset, in ns."""
        return int(round(convention_offset_s(self.interval) * 1e9))

    def twist(self, omega_l, omega_r) -> np.ndarray:
        return get_model('edd_symmetric').bind(TRUE_PARAMS, GEOMETRY).twist(omega_l, omega_r)

    def intervals(self, t_ns: np.ndarray, omega_l: np.ndarray, omega_r: np.ndarray,
                  dt_s: np.ndarray, restart: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        held = np.zeros(np.shape(omega_l) + (3,))
        for row in range(held.shape[0]):
            t_s = (t_ns[row] - t_ns[row, 0]) * 1e-9
            held[row], _ = apply_effects(self.effects, t_s, omega_l[row], omega_r[row],
                                         self.twist, lambda twist: twist, self.duration_s)
        return held, held


def true_source(effects: Effect | Sequence[Effect] | None, duration_s: float,
                interval: str = SIM_INTERVAL):
    """Return the true model to score: :func:`true_state` bound, or :class:`SimulatorTruth`."""
    effects = _as_effects(effects)
    if all(effect.name in _EXACT for effect in effects):
        return true_state(effects, duration_s, interval).bind('edd_symmetric', GEOMETRY)
    return SimulatorTruth(effects, duration_s, interval)


def drawn_effect(name: str) -> Effect:
    """Return the effect at a strength drawn uniformly in its range (seeded per effect)."""
    spec = EFFECTS[name]
    rng = np.random.default_rng([STRENGTH_SEED, EFFECT_NAMES.index(name)])
    return make_effect(name, float(rng.uniform(spec.low, spec.high)))


def case_effects(case: str) -> tuple[Effect, ...]:
    """Return the effects of a case name (``none``, an effect, effects joined by ``+``)."""
    if case == 'none':
        return ()
    names = case.split('+')
    unknown = [name for name in names if name not in EFFECTS]
    if unknown:
        raise ParameterError(f'unknown effect(s) {unknown} in case {case!r}; known: '
                             f'{", ".join(EFFECT_NAMES)}')
    return tuple(drawn_effect(name) for name in names)


TABLE_HEADER = ('| injected | found | eps_t m/m: base -> augmented (true model) | '
                'eps_theta deg/m: base -> augmented (true model) |', '|---|---|---|---|')


@dataclass(frozen=True)
class EffectCase:
    """One row of the study: the diagnosis and the true model's errors on the same segments."""

    effects: tuple[Effect, ...]
    result: DiagnosisResult
    truth_t: ErrorStats
    truth_theta: ErrorStats

    def row(self) -> str:
        """Return the case's row of the results table (held-out medians, base -> augmented)."""
        first, last = self.result.steps[0], self.result.steps[-1]
        found = ', '.join(self.result.extensions) or 'nothing'
        found += ''.join(f'; unexplained: {lead.signal} {lead.share:.0%}'
                         for lead in self.result.unexplained)
        label = ' + '.join(f'{e.name} {e.strength:.3g}' for e in self.effects) or 'none'
        return (f'| {label} | {found} | {first.stats_t.median:.4f} -> '
                f'{last.stats_t.median:.4f} ({self.truth_t.median:.4f}) | '
                f'{first.stats_theta.median:.3f} -> {last.stats_theta.median:.3f} '
                f'({self.truth_theta.median:.3f}) |')


def run_case(effects: Effect | Sequence[Effect] | None, duration_s: float = 120.0,
             options: DiagnosisOptions | None = None) -> EffectCase:
    effects = _as_effects(effects)
    train = sim_drives(effects, [1, 2], duration_s)
    evaluate = sim_drives(effects, [3, 4, 5], duration_s)
    options = options or DiagnosisOptions(interval=SIM_INTERVAL)
    base = fit_model('edd_symmetric', GEOMETRY, cut_segments(train, options.train_segments()))
    result = diagnose(train, evaluate, GEOMETRY, {'edd_symmetric': base.values}, 'edd_symmetric',
                      options)
    predictor = SegmentPredictor(evaluate, cut_segments(evaluate, options.eval_segments()),
                                 interval=options.interval)
    errors = predictor.errors(true_source(effects, duration_s, options.interval))
    eps_t, eps_theta = relative_errors(errors, predictor.segments.path_m,
                                       options.min_eval_path_m)
    return EffectCase(effects, result, ErrorStats.of(eps_t), ErrorStats.of(eps_theta))


def run_study(names: Sequence[str | None] = CASE_NAMES) -> Iterator[EffectCase]:
    """Run the cases in order (None or 'none': effect-free data), effects at drawn strengths."""
    for name in names:
        yield run_case(case_effects(name or 'none'))
