"""The diagnosis recipe: refit, trace, select, and measure before and after.

:func:`diagnose` runs the steps of :mod:`skidkin_ros.core.calibration.diagnosis` in order; each
step's module says how and why. The stamp convention is decided here: under ``interval:
starting`` (a zero-order hold from the stamp), a wheel speed held from its stamp describes the
middle of the interval it is held over, so effect-free data gains from a -dt/2 time offset. That
offset is part of the baseline (its own row in the table), never a found effect. Under
``ending`` or ``midpoint`` (:mod:`skidkin_ros.core.odometry.interval`) no offset is needed and
there is no such row.
"""

from __future__ import annotations

from dataclasses import replace
import time
from typing import Mapping, Sequence

import numpy as np

from skidkin_ros import __version__
from skidkin_ros.core.calibration.diagnosis.base import question_base
from skidkin_ros.core.calibration.diagnosis.candidates import CandidateFitter
from skidkin_ros.core.calibration.diagnosis.options import DiagnosisOptions
from skidkin_ros.core.calibration.diagnosis.residuals import pose_residuals, pose_samples
from skidkin_ros.core.calibration.diagnosis.results import DiagnosisResult, ModelStep
from skidkin_ros.core.calibration.diagnosis.select_extensions import Progress, select
from skidkin_ros.core.calibration.diagnosis.state import fit_state, ModelState
from skidkin_ros.core.calibration.diagnosis.tracing import (correlations, lag_scan,
                                                            residual_leads, Trace)
from skidkin_ros.core.calibration.engine import trim_mask
from skidkin_ros.core.calibration.evaluation import ErrorStats, relative_errors
from skidkin_ros.core.calibration.holdout import resolve_holdout
from skidkin_ros.core.calibration.predictor import SegmentPredictor
from skidkin_ros.core.calibration.segments import usable_segments
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.kinematics.extensions import FitHints
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.parallel import one_blas_thread
from skidkin_ros.core.scratch import kept_heap

__all__ = ['diagnose', 'wheel_period_s']

# A diagnosis needs at least this many training and evaluation segments.
MIN_SEGMENTS = 6


def wheel_period_s(drives: Sequence[Drive]) -> float:
    """Return the median wheel sample period (s) of the drives, 0 without samples."""
    steps = [np.diff(d.wheels.t_ns) for d in drives if len(d.wheels) > 1]
    steps = np.concatenate(steps) if steps else np.zeros(0)
    steps = steps[steps > 0]
    return float(np.median(steps)) * 1e-9 if steps.size else 0.0


def _stamp_convention(drives: Sequence[Drive], options: DiagnosisOptions) -> float:
    """Return -dt/2 (s) for options.stamp_convention 'mid' under the ``starting`` interval, else 0.

    Only the zero-order hold from the stamp (``interval: starting``) lags by half a sample; the
    ``ending`` and ``midpoint`` conventions need no offset.
    """
    if options.stamp_convention != 'mid' or options.interval != 'starting':
        return 0.0
    return -0.5 * wheel_period_s(drives)


def _evaluate(predictor: SegmentPredictor, label: str, state: ModelState, base_name: str,
              geometry: Geometry, options: DiagnosisOptions) -> ModelStep:
    errors = predictor.errors(state.bind(base_name, geometry))
    eps_t, eps_th = relative_errors(errors, predictor.segments.path_m, options.min_eval_path_m)
    return ModelStep(label, state, eps_t, eps_th, ErrorStats.of(eps_t), ErrorStats.of(eps_th))


def _refit_without_outliers(predictor: SegmentPredictor, base_name: str, geometry: Geometry,
                            refit: ModelState, options: DiagnosisOptions
                            ) -> tuple[ModelState, int]:
    """Refit the base model without its outlier segments (C15, C211); return (it, trimmed).

    Calibrate fits the base model without its outlier segments (ground-truth glitches); a
    least-squares refit on every segment lets a few of them pull the base away from it (on the
    Husky, b_hat 1.170 -> 1.197 and 14 % more held-out heading error), and every extension is
    then built on that. The extensions are still selected on every segment (``trim`` drops the
    outliers from the selection too).
    """
    kept = trim_mask(predictor.errors(refit.bind(base_name, geometry)), options.whitening)
    if kept.all():
        return refit, 0
    fitted, _ = fit_state(predictor, base_name, geometry, refit, options,
                          keep=np.nonzero(kept)[0])
    return fitted, int((~kept).sum())


def _parameter_count(state: ModelState) -> int:
    """Return how many values a path's final state fits (base values and every extension's)."""
    return len(state.base_values) + sum(len(values) for values in state.ext_values.values())


def _other_path_wins(ratio_given: float, ratio_other: float, count_given: int, count_other: int,
                     margin: float) -> bool:
    """Return whether the other base's path replaces the given one's (see the recipe).

    Lower held-out loss by more than ``margin`` wins; within it, fewer parameters; on a tie of
    both, the given model stays.
    """
    if ratio_other < (1.0 - margin) * ratio_given:
        return True
    if ratio_given < (1.0 - margin) * ratio_other:
        return False
    return count_other < count_given


def _path_ratio(candidates: Sequence) -> float:
    """Return the held-out loss after the accepted extensions relative to before them."""
    ratio = 1.0
    for score in candidates:
        if score.accepted:
            ratio *= 1.0 - score.relative_gain
    return ratio


def diagnose(train: Sequence[Drive], evaluate: Sequence[Drive] | None, geometry: Geometry,
             base_values_by_model: Mapping[str, Mapping[str, float]], base_model_name: str,
             options: DiagnosisOptions | None = None, jobs: int = 1,
             progress: Progress | None = None) -> DiagnosisResult:
    """Run the diagnosis recipe of the package docstring and return its result.

    ``jobs``: how many processes fit the candidates (the result does not depend on it);
    ``progress(round, done, total)`` is called as each fit of a selection round finishes. Its
    matrices are small: numpy's BLAS runs on one thread (several spin against each other on a
    loaded machine, 250 ms for a 2500 x 20 Gram matrix instead of 0.2 ms).
    """
    with one_blas_thread(), kept_heap():
        return _diagnose(train, evaluate, geometry, base_values_by_model, base_model_name,
                         options, jobs, progress)


def _diagnose(train: Sequence[Drive], evaluate: Sequence[Drive] | None, geometry: Geometry,
              base_values_by_model: Mapping[str, Mapping[str, float]], base_model_name: str,
              options: DiagnosisOptions | None, jobs: int,
              progress: Progress | None) -> DiagnosisResult:
    options = options or DiagnosisOptions()
    model = get_model(base_model_name)
    given = dict(base_values_by_model.get(base_model_name, {}))
    model.vector(given, geometry)
    train, evaluate, holdout = resolve_holdout(train, evaluate, options.holdout_every,
                                               options.holdout_mode, options.holdout_block_s,
                                               options.holdout_key)
    tic = time.perf_counter()
    train_seg = usable_segments(train, options.train_segments(), 'training', MIN_SEGMENTS,
                                'a diagnosis')
    eval_seg = usable_segments(evaluate, options.eval_segments(), 'evaluation', MIN_SEGMENTS,
                               'a diagnosis')
    given_state = ModelState((), given, {})
    convention_s = _stamp_convention(train, options)
    predictor = SegmentPredictor(train, train_seg, options.max_dt_s,
                                 options.interval)
    refit, _ = fit_state(predictor, base_model_name, geometry, given_state, options)
    trimmed = base_trimmed = 0
    if options.trim:
        # Outlier segments (e.g. ground-truth glitches, C15) are dropped once, as calibrate does.
        kept = trim_mask(predictor.errors(refit.bind(base_model_name, geometry)),
                         options.whitening)
        trimmed = int((~kept).sum())
        if trimmed:
            train_seg = train_seg.subset(kept)
            predictor = SegmentPredictor(train, train_seg, options.max_dt_s,
                                         options.interval)
            refit, _ = fit_state(predictor, base_model_name, geometry, refit, options)
    else:
        refit, base_trimmed = _refit_without_outliers(predictor, base_model_name, geometry,
                                                      refit, options)
    given_name = base_model_name
    base_scores: tuple = ()
    switched = None
    if options.question_base:
        other, switched, base_scores = question_base(
            train, predictor, geometry, base_model_name, base_values_by_model, options, jobs)
    durations = [d.duration_s() for d in train]

    def explore(name: str, start: ModelState, rounds: int | None = None):
        """Trace the residuals of a base model and select its extensions (``rounds``: at most)."""
        chosen = options if rounds is None else replace(options, max_extensions=rounds)
        null = start
        if convention_s != 0.0:
            null = ModelState(('time_offset',), dict(start.base_values),
                              {'time_offset': {'offset_s': convention_s}})
            null, _ = fit_state(predictor, name, geometry, null, options)
        samples = pose_samples(train, start.bind(name, geometry), options)
        residual, valid = pose_residuals(train, samples, null.bind(name, geometry), options)
        lag_s, curve = lag_scan(train, samples, start, name, geometry, options)
        lag_s -= convention_s
        trace = Trace(residual, samples.signals, correlations(residual, valid, samples.signals),
                      lag_s, curve, predictor.errors(null.bind(name, geometry)))
        hints = FitHints(lag_s, convention_s, wheel_period_s(train),
                         max(durations) if durations else 0.0)
        fitter = CandidateFitter(train, train_seg, name, geometry, chosen, samples, hints)
        return (null, samples, residual, valid, trace) + select(fitter, null, jobs, progress)

    explored = explore(base_model_name, refit)
    if switched is not None:
        # The base model is questioned as an extension is, and against what the extensions make
        # of the given one: each path's held-out loss relative to the given model alone is the
        # product of its steps' ratios (the base model's, then each accepted extension's). A path
        # that ends lower by more than min_relative_gain wins; within that margin the path with
        # fewer parameters wins (the simpler explanation), the given one on a tie. Comparing
        # whole paths, not the first round, matters when the residual model can stand in for
        # the base: it mimics an asymmetry with many coefficients, where the right base needs
        # a few; and a base that passes only because it mimics an extension (roc's ICR for a
        # lateral skid) ends level with the given one plus that extension, and is not taken.
        gain_base = max(score.gain for score in base_scores if score.accepted)
        other_explored = explore(other, switched)
        ratio_given = _path_ratio(explored[6])
        ratio_other = (1.0 - gain_base) * _path_ratio(other_explored[6])
        if _other_path_wins(ratio_given, ratio_other, _parameter_count(explored[5]),
                            _parameter_count(other_explored[5]), options.min_relative_gain):
            base_model_name, refit, explored = other, switched, other_explored
        else:
            base_scores = tuple(replace(score, accepted=False, note=(
                f'passes, but the given model with its extensions explains as much or more: '
                f'held-out loss x{ratio_given:.2f} against x{ratio_other:.2f} on {other} with '
                f'its own'))
                if score.accepted else score for score in base_scores)
    null, samples, residual, valid, trace, final, scores, accepted = explored
    eval_predictor = SegmentPredictor(evaluate, eval_seg, options.max_dt_s,
                                      options.interval)
    replaced = f'; replaces {given_name}' if base_model_name != given_name else ''
    steps = [_evaluate(eval_predictor, f'{given_name} (given)', given_state,
                       given_name, geometry, options),
             _evaluate(eval_predictor, f'{base_model_name} (refitted{replaced})', refit,
                       base_model_name, geometry, options)]
    if convention_s != 0.0:
        steps.append(_evaluate(eval_predictor, f'+ stamp convention {convention_s * 1e3:+.0f} ms',
                               null, base_model_name, geometry, options))
    for state in accepted:
        label = '+ ' + ' + '.join(state.found)
        steps.append(_evaluate(eval_predictor, label, state, base_model_name, geometry,
                               options))
    after, after_valid = pose_residuals(train, samples, final.bind(base_model_name, geometry),
                                        options)
    unexplained = residual_leads(after, after_valid, samples.signals, geometry)
    warnings = []
    if accepted and steps[-1].stats_t.median > steps[1].stats_t.median * 1.05:
        warnings.append('the augmented model is worse than the refitted base model on the '
                        'evaluation drives (median eps_t); the effect may not transfer')
    provenance = {
        'tool': f'skidkin_ros {__version__}', 'base_model': base_model_name,
        'given_base_model': given_name,
        'base_models_questioned': [f'{s.name}: held-out gain {s.gain:+.3f}, p {s.p_value:.2g}'
                                   + (' (replaces the given model)' if s.accepted else '')
                                   + (f' ({s.note})' if s.note else '')
                                   for s in base_scores],
        'extensions': list(final.found), 'model_extensions': list(final.extensions),
        'stamp_convention_s': convention_s, 'train_drives': len(train),
        'evaluate_drives': len(evaluate), 'train_segments': len(train_seg),
        'train_segments_trimmed': trimmed, 'base_refit_segments_trimmed': base_trimmed,
        'evaluate_segments': len(eval_seg), 'holdout': holdout,
        'unexplained': [f'{lead.signal} ({lead.component} residual): share {lead.share:.3f}, '
                        f'r {lead.r:+.3f}' for lead in unexplained],
        'seconds': round(time.perf_counter() - tic, 2), 'options': options.as_dict(),
    }
    return DiagnosisResult(base_model_name, geometry, options, trace, tuple(scores),
                           tuple(steps), final, after, valid, after_valid, holdout,
                           tuple(warnings), provenance, unexplained)
