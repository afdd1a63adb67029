"""The calibration pipeline, as a recipe: segment, fit, evaluate, calibrate noise, pick the best.

``calibrate(train, evaluate, geometry, options)``:

1. cut the training drives into segments (``segments``): ``rotation`` (default) closes a segment
   after h_t of path or ``h_t_rad`` of turning, whichever comes first, so spins in place still
   make segments and their yaw is fitted; ``paper`` by path alone (Baril et al. 2020); ``time``
   by windows of ``window_s``. Stationary and invalid segments are dropped (counted); a drive
   with no full segment is one segment (``short_drive``). docs/calibration-segments.md has the
   held-out comparison that chose the default;
2. fit the requested models on them (skidkin_ros.core.calibration.fitting);
3. cut the evaluation drives (a deterministic hold-out of the training drives when none are given)
   into segments of h_e and score every model on the same segments (eps_t, eps_theta);
4. calibrate each model's noise on its evaluation residuals at several horizons
   (``noise_horizon_factors`` times h_e: a variance per metre and a length-independent part),
   with the fit's own parameter covariance as a fixed term, and check it two-fold per horizon
   (average NEES against its chi2 band; a warning says when the held-out data are too few to
   support the claim, or disagree with it); measure the errors at the end of held-out windows
   of ``window_s`` (heading drift);
5. pick the best model by the rule below;
6. with a gyro in the training data: fit its scale, bias and time offset on the training drives
   and, with the best model, the gyro modes' noise on the evaluation drives
   (:mod:`skidkin_ros.core.calibration.gyro_fit`);
7. fit the written model the plain way a user would (one segment per training window of
   ``window_s``, unit weights, no trimming, the best of several starts) and score it on the
   same held-out window ends: the
   reference the written model must not lose to (``plain_window_end``, printed beside it).

The fit (step 2) is the iterated one of :mod:`skidkin_ros.core.calibration.weighting` (each
segment weighted by the covariance the noise model predicts for it) unless ``weighting`` is
``fixed`` (the loss covariance ``sigma_diag`` for every segment, as before).

Best-model rule (``selection: likelihood``, :mod:`skidkin_ros.core.calibration.selection`): the
lowest held-out negative log-likelihood per segment among the valid fits; a model with fewer
parameters is taken when it is within 2 paired standard errors (clustered by drive or hold-out
group). When the likelihood cannot be computed (too little held-out data) or with ``selection:
paper``: score each valid model by median eps_t / (best median eps_t) + median eps_theta /
(best median eps_theta); the lowest score wins, and when two scores are within 2 % the model
with fewer parameters wins (the paper's argument for the symmetric EDD).

The sample-interval convention (``options.interval``,
:mod:`skidkin_ros.core.odometry.interval`) is part of the model: :func:`calibrate_interval`
chooses it on the held-out data. It calibrates under ``ending`` (the default), refits the model
that won under ``starting`` and ``midpoint`` on the same segments, scores the three by the paper's
rule on the model's held-out errors (median eps_t / best + median eps_theta / best; within 2 %
of the lowest, ``ending`` is kept, then the order of :data:`INTERVALS`), and returns the
calibration under the winner; the parameters file records it (``interval``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import logging
import math
from typing import Mapping, Sequence

import numpy as np

from skidkin_ros import __version__
from skidkin_ros.core.calibration.evaluation import (evaluate_models, ModelEvaluation,
                                                     window_end_errors, WindowEnd)
from skidkin_ros.core.calibration.fitting import FitResult
from skidkin_ros.core.calibration.gyro_fit import GyroFit
from skidkin_ros.core.calibration.holdout import resolve_holdout
from skidkin_ros.core.calibration.noise_fit import calibrate_noise, NoiseFit
from skidkin_ros.core.calibration.noise_notes import band_notes, noise_warnings
from skidkin_ros.core.calibration.results import (CalibrationOptions, CalibrationResult,
                                                  INTERVAL_SEARCHES, result_to_parameters,
                                                  SELECTIONS, TRAIN_SEGMENTS)
from skidkin_ros.core.calibration.segments import cut_segments, SegmentSet, usable_segments
from skidkin_ros.core.calibration.selection import (choose_by_likelihood, heldout_nll,
                                                    Likelihood, paper_scores, paper_ties,
                                                    segment_clusters)
from skidkin_ros.core.calibration.steps import (_add_gyro, _add_plain_reference, _fit_gyro_outcome,
                                                _GYRO_TASK, _jobs, plain_window_fit)
from skidkin_ros.core.calibration.weighting import fit_models_weighted
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.interval import INTERVALS
from skidkin_ros.core.parallel import fork_map
from skidkin_ros.errors import DataError, FitError, ParameterError

__all__ = ['band_notes', 'CalibrationOptions', 'CalibrationResult', 'calibrate', 'choose_best',
           'noise_warnings',
           'calibrate_interval', 'choose_interval', 'INTERVAL_SEARCHES', 'TRAIN_SEGMENTS',
           'plain_window_fit',
           'result_to_parameters', 'horizon_study', 'HorizonStudy', 'SELECTIONS']

LOG = logging.getLogger(__name__)


def choose_best(fits: Mapping[str, FitResult],
                evaluation: Mapping[str, ModelEvaluation]) -> tuple[str, dict[str, float]]:
    """Apply the best-model rule of the module docstring; return (best, scores)."""
    valid = [m for m in evaluation if fits[m].valid
             and math.isfinite(evaluation[m].stats_t.median)]
    if not valid:
        raise FitError('no model produced a valid fit with finite evaluation errors; see the '
                       'warnings')
    scores = paper_scores({m: (evaluation[m].stats_t.median, evaluation[m].stats_theta.median)
                           for m in valid})
    tied = paper_ties(scores, valid)
    best = min(tied, key=lambda m: (len(get_model(m).params), scores[m]))
    return best, scores


def choose_interval(errors: Mapping[str, tuple[float, float]]) -> tuple[str, dict[str, float]]:
    """Return the convention the module docstring's rule picks, and each one's score.

    ``errors``: held-out median (eps_t, eps_theta) of one model under each convention.
    """
    finite = {k: v for k, v in errors.items() if math.isfinite(v[0]) and math.isfinite(v[1])}
    if not finite:
        raise FitError('no sample-interval convention gave finite held-out errors')
    scores = paper_scores(finite)
    return paper_ties(scores, INTERVALS)[0], scores


def calibrate_interval(train: Sequence[Drive], evaluate: Sequence[Drive] | None,
                       geometry: Geometry, options: CalibrationOptions | None = None,
                       intervals: Sequence[str] = INTERVALS,
                       interval_search: str = 'fits') -> CalibrationResult:
    """Calibrate and choose the sample-interval convention on held-out data (module docstring).

    ``intervals``: the conventions to try, the first one calibrated with every model; one name
    calibrates under it alone. ``interval_search``: ``fits`` (default) compares the other
    conventions by refitting and scoring the winning model alone, and calibrates the gyro once,
    under the chosen convention; ``full`` runs the whole recipe for each (the earlier way,
    kept so the benchmark can time it beside: same choice, about twice the work).
    """
    options = options or CalibrationOptions()
    if interval_search not in INTERVAL_SEARCHES:
        raise ParameterError(f'interval_search must be one of {INTERVAL_SEARCHES}, got '
                             f'{interval_search!r}')
    intervals = tuple(dict.fromkeys(intervals))
    if interval_search == 'full':
        return _calibrate_interval_full(train, evaluate, geometry, options, intervals)
    train, evaluate, holdout = resolve_holdout(train, evaluate, options.holdout_every,
                                               options.holdout_mode, options.holdout_block_s,
                                               options.holdout_key)
    stage = _fit_stage(train, evaluate, holdout, geometry,
                       replace(options, interval=intervals[0]), gyro=True,
                       with_noise=len(intervals) == 1)
    gyro = stage.gyro
    if len(intervals) == 1:
        return _add_gyro(_noise_stage(stage), train, evaluate, gyro, plain=True)
    model = stage.best
    errors = {intervals[0]: _median_errors(stage.done[model].evaluation)}
    refits = {}
    # the other conventions' refits are independent: parallel tasks
    others = fork_map(lambda interval: _interval_errors(
        model, train, evaluate, geometry, replace(options, interval=interval)),
        intervals[1:], _jobs(options.jobs))
    for interval, (error, fit) in zip(intervals[1:], others):
        errors[interval], refits[interval] = error, fit
    chosen, _ = choose_interval(errors)
    if chosen != intervals[0]:
        # the gyro fit does not depend on the convention: kept; the noise is calibrated
        # only under the convention that is written, so each model's noise is calibrated in
        # the task that fits it (no wait for the other fits); the model refitted under it to
        # compare the conventions is the same fit (same segments and options): not fitted again
        stage = _fit_stage(train, evaluate, holdout, geometry, replace(options, interval=chosen),
                           known_fits={model: refits[chosen]}, with_noise=True)
    return _add_gyro(_with_interval_errors(_noise_stage(stage), errors), train, evaluate, gyro,
                     plain=True)


def _median_errors(stats: ModelEvaluation) -> tuple[float, float]:
    return float(stats.stats_t.median), float(stats.stats_theta.median)


def _interval_errors(model: str, train: Sequence[Drive], evaluate: Sequence[Drive],
                     geometry: Geometry, options: CalibrationOptions
                     ) -> tuple[tuple[float, float], FitResult]:
    """Held-out median (eps_t, eps_theta) of one model fitted under ``options.interval``.

    The same fit and scoring as :func:`calibrate` (its step 2 and 3), without the rest; the
    fit is returned too.
    """
    train_seg = usable_segments(train, options.train_segments(), 'training',
                                needed_by='a calibration')
    eval_seg = usable_segments(evaluate, options.eval_segments(), 'evaluation',
                               needed_by='a calibration')
    fits = fit_models_weighted(geometry, train_seg, options.fit_options(), (model,),
                               options.weighting)
    evaluation = evaluate_models({model: fits[model].values}, geometry, eval_seg,
                                 options.min_eval_path_m)
    return _median_errors(evaluation[model]), fits[model]


def _with_interval_errors(result: CalibrationResult,
                          errors: Mapping[str, tuple[float, float]]) -> CalibrationResult:
    provenance = dict(result.provenance)
    provenance['interval_errors'] = {k: [round(v[0], 6), round(v[1], 6)]
                                     for k, v in errors.items()}
    return replace(result, provenance=provenance, interval_errors=dict(errors))


def _calibrate_interval_full(train: Sequence[Drive], evaluate: Sequence[Drive] | None,
                             geometry: Geometry, options: CalibrationOptions,
                             intervals: tuple[str, ...]) -> CalibrationResult:
    """Run the earlier search: the whole recipe per convention (``interval_search='full'``)."""
    first = calibrate(train, evaluate, geometry, replace(options, interval=intervals[0]))
    if len(intervals) == 1:
        return first
    model = first.best
    errors = {}
    for interval in intervals:
        result = first if interval == intervals[0] else calibrate(
            train, evaluate, geometry, replace(options, interval=interval, models=(model,)))
        errors[interval] = _median_errors(result.evaluation[model])
    chosen, _ = choose_interval(errors)
    if chosen != intervals[0]:
        first = calibrate(train, evaluate, geometry, replace(options, interval=chosen))
    return _with_interval_errors(first, errors)


def calibrate(train: Sequence[Drive], evaluate: Sequence[Drive] | None, geometry: Geometry,
              options: CalibrationOptions | None = None) -> CalibrationResult:
    """Run the whole calibration recipe (module docstring) and return its result."""
    options = options or CalibrationOptions()
    train, evaluate, holdout = resolve_holdout(train, evaluate, options.holdout_every,
                                               options.holdout_mode, options.holdout_block_s,
                                               options.holdout_key)
    result, gyro = _calibrate_resolved(train, evaluate, holdout, geometry, options, gyro=True)
    return _add_plain_reference(_add_gyro(result, train, evaluate, gyro), train, evaluate)


def _calibrate_resolved(train: Sequence[Drive], evaluate: Sequence[Drive], holdout: str,
                        geometry: Geometry, options: CalibrationOptions,
                        gyro: bool = False
                        ) -> tuple[CalibrationResult, GyroFit | str | None]:
    """Run steps 1-5 of the recipe on drives already split into training and evaluation.

    ``gyro``: also fit the gyro on the training drives (step 6's first part, independent of
    the models), as one more parallel task. Returns (result, the gyro fit or why there is none;
    None when not asked or without a gyro), for :func:`_add_gyro`.
    """
    stage = _fit_stage(train, evaluate, holdout, geometry, options, gyro, with_noise=True)
    return _noise_stage(stage), stage.gyro


@dataclass(frozen=True)
class _Stage:
    """The fits, scores and model choice of one convention, before the noise (step 4)."""

    train: Sequence[Drive]
    evaluate: Sequence[Drive]
    holdout: str
    options: CalibrationOptions
    work: '_ModelWork'
    models: tuple[str, ...]
    done: Mapping[str, '_ModelResult']
    best: str
    scores: dict[str, float]
    likelihood: dict[str, Likelihood]
    rule: str
    selection_warnings: tuple[str, ...]
    gyro: GyroFit | str | None


def _fit_stage(train: Sequence[Drive], evaluate: Sequence[Drive], holdout: str,
               geometry: Geometry, options: CalibrationOptions, gyro: bool = False,
               known_fits: Mapping[str, FitResult] | None = None,
               with_noise: bool = False) -> _Stage:
    """Run steps 1-3 and 5: fit, score and choose, each model a parallel task (and the gyro).

    ``known_fits``: models already fitted under these ``options`` (the same call of
    :func:`fit_models_weighted`), scored without fitting them again. ``with_noise``: each
    task also calibrates its model's noise (step 4, the same call :func:`_noise_stage` makes),
    for a stage whose noise is sure to be needed.
    """
    train_seg = usable_segments(train, options.train_segments(), 'training',
                                needed_by='a calibration')
    eval_seg = usable_segments(evaluate, options.eval_segments(), 'evaluation',
                               needed_by='a calibration')
    models = tuple(dict.fromkeys(('ideal_dd',) + tuple(options.models)))
    windows = cut_segments(evaluate, replace(options.eval_segments(), horizon_s=options.window_s))
    other = {h: cut_segments(evaluate, seg) for h, seg in options.noise_horizons().items()}
    clusters = None
    if options.selection == 'likelihood':
        clusters = segment_clusters(eval_seg, evaluate, options.holdout_key)
    work = _ModelWork(geometry, options, train_seg, eval_seg, windows, other, clusters,
                      tuple(train) if gyro else (), dict(known_fits or {}), with_noise)
    # The costliest tasks first, so the workers finish together.
    order = sorted(models, key=lambda m: -len(get_model(m).params))
    if gyro and any(drive.imu is not None for drive in train):
        order = [_GYRO_TASK] + order
    done = dict(zip(order, fork_map(work, order, _jobs(options.jobs))))
    gyro_outcome = done.pop(_GYRO_TASK, None)
    fits = {m: done[m].fit for m in models}
    best, scores = choose_best(fits, {m: done[m].evaluation for m in models})
    likelihood, rule, notes = {}, 'paper', []
    if options.selection == 'likelihood':
        try:
            best, likelihood = _choose_by_likelihood(fits, done, clusters)
            rule = 'likelihood'
        except DataError as err:
            notes.append(f'best model chosen on eps_t and eps_theta: {err}')
    return _Stage(train, evaluate, holdout, options, work, models, done, best, scores,
                  likelihood, rule, tuple(notes), gyro_outcome)


def _noise_stage(stage: _Stage) -> CalibrationResult:
    """Step 4 for every model (parallel tasks), then the result of steps 1-5."""
    options, work, models, done = stage.options, stage.work, stage.models, stage.done
    fits = {m: done[m].fit for m in models}
    order = [m for m in sorted(models, key=lambda m: -len(get_model(m).params))
             if done[m].noise is None]
    calibrated = dict(zip(order, fork_map(work, [(_NOISE_TASK, m, fits[m]) for m in order],
                                          _jobs(options.jobs))))
    calibrated.update({m: done[m].noise for m in models if done[m].noise is not None})
    noise = {m: calibrated[m][0] for m in models if calibrated[m][0] is not None}
    warnings = [w for m in models for w in fits[m].warnings]
    for m in models:
        warnings += calibrated[m][1]
    counts = work.train_seg.counts
    if counts.stationary:
        warnings.append(f'{counts.stationary} training segment(s) without motion were excluded')
    warnings += stage.selection_warnings
    best = stage.best
    if best in noise:
        sets = {**work.other, options.h_e: work.eval_seg}
        warnings += band_notes(noise[best], {h: s.path_m for h, s in sets.items()})
    provenance = {
        'tool': f'skidkin_ros {__version__}',
        'train_drives': len(stage.train), 'evaluate_drives': len(stage.evaluate),
        'train_segments': len(work.train_seg), 'evaluate_segments': len(work.eval_seg),
        'holdout': stage.holdout, 'options': options.as_dict(),
        'noise_coverage_scale': {name: round(nf.coverage_scale, 4) for name, nf in noise.items()},
        'noise_heldout_horizons_m': [options.h_e * f for f in
                                     sorted(set(options.noise_horizon_factors) | {1.0})],
        'noise_heldout_nees': {name: [round(c.mean_nees, 3) for c in nf.consistency.horizons]
                               for name, nf in noise.items()},
    }
    provenance['selection'] = stage.rule
    return CalibrationResult(work.geometry, options, fits,
                             {m: done[m].evaluation for m in models}, noise, best, stage.scores,
                             tuple(warnings), work.train_seg, work.eval_seg, stage.holdout,
                             provenance, stage.likelihood,
                             {m: done[m].window_end for m in models}, stage.rule,
                             eval_truth=tuple(drive.truth for drive in stage.evaluate))


_NOISE_TASK = '(noise)'


@dataclass(frozen=True)
class _ModelResult:
    """Everything :func:`calibrate` computes for one model on its own (one task)."""

    fit: FitResult
    evaluation: ModelEvaluation
    window_end: WindowEnd
    nll: np.ndarray | None
    nll_error: str | None
    noise: tuple[NoiseFit | None, tuple[str, ...]] | None = None  # with_noise: step 4 too


@dataclass(frozen=True)
class _ModelWork:
    """One model's fit, scores, held-out likelihood, or noise: independent of the others.

    So the models are calibrated in parallel (forked workers,
    :func:`skidkin_ros.core.parallel.fork_map`); the result does not depend on their number.
    """

    geometry: Geometry
    options: CalibrationOptions
    train_seg: SegmentSet
    eval_seg: SegmentSet
    windows: SegmentSet
    other: Mapping[float, SegmentSet]
    clusters: np.ndarray | None
    gyro_train: tuple[Drive, ...] = ()
    known_fits: Mapping[str, FitResult] = field(default_factory=dict)
    with_noise: bool = False

    def __call__(self, item):
        """Run one task: a model's fit and scores, a model's noise (a tuple), or the gyro."""
        if item == _GYRO_TASK:
            return _fit_gyro_outcome(self.gyro_train)
        if isinstance(item, tuple):
            _, name, fit = item
            return self.noise(name, fit)
        return self.fit(item)

    def fit(self, name: str) -> _ModelResult:
        options, geometry = self.options, self.geometry
        fit = self.known_fits.get(name)
        if fit is None:
            fit = fit_models_weighted(geometry, self.train_seg, options.fit_options(), (name,),
                                      options.weighting)[name]
        evaluation = evaluate_models({name: fit.values}, geometry, self.eval_seg,
                                     options.min_eval_path_m)[name]
        window_end = window_end_errors(name, fit.values, geometry, self.windows)
        nll, nll_error = None, None
        if self.clusters is not None and fit.valid:
            try:
                nll = heldout_nll(name, fit.values, geometry, self.eval_seg, self.clusters)
            except DataError as err:
                nll_error = str(err)
        noise = self.noise(name, fit) if self.with_noise else None
        return _ModelResult(fit, evaluation, window_end, nll, nll_error, noise)

    def noise(self, name: str, fit: FitResult) -> tuple[NoiseFit | None, tuple[str, ...]]:
        options = self.options
        param_cov = fit.covariance if options.parameter_covariance else None
        try:
            noise = calibrate_noise(name, fit.values, self.geometry, self.eval_seg, self.other,
                                    param_cov, options.h_e, options.noise_constant,
                                    options.noise_time)
        except DataError as err:
            return None, (f'{name}: noise model not calibrated: {err}',)
        return noise, tuple(noise_warnings(noise))


def _choose_by_likelihood(fits: Mapping[str, FitResult], done: Mapping[str, _ModelResult],
                          clusters: np.ndarray) -> tuple[str, dict[str, Likelihood]]:
    """Held-out NLL of every valid fit, then the rule of selection.choose_by_likelihood."""
    valid = [m for m, f in fits.items() if f.valid]
    errors = [done[m].nll_error for m in valid if done[m].nll_error]
    if errors:
        raise DataError(errors[0])
    if np.unique(clusters).size < 2:
        raise DataError('the held-out likelihood needs evaluation data from at least 2 drives '
                        'or hold-out groups')
    nll = {m: done[m].nll for m in valid}
    return choose_by_likelihood(nll, clusters, {m: len(get_model(m).params) for m in valid})


@dataclass(frozen=True)
class HorizonStudy:
    """Median and interquartile range of eps_t for each (model, h_t, h_e)."""

    h_t: tuple[float, ...]
    h_e: tuple[float, ...]
    median: dict[str, np.ndarray]   # model -> (len(h_t), len(h_e))
    iqr: dict[str, np.ndarray]


def horizon_study(train: Sequence[Drive], evaluate: Sequence[Drive], geometry: Geometry,
                  options: CalibrationOptions, h_t_values: Sequence[float],
                  h_e_values: Sequence[float]) -> HorizonStudy:
    """Train at several h_t and evaluate at several h_e (the paper's horizon figure).

    The segments are cut as :func:`calibrate` cuts them (``options.train_segments()`` and
    ``eval_segments()``, the sample-interval convention included), only the horizon changes.
    """
    models = tuple(m for m in options.models if get_model(m).params) or ('ideal_dd',)
    shape = (len(h_t_values), len(h_e_values))
    median = {m: np.full(shape, np.nan) for m in models}
    iqr = {m: np.full(shape, np.nan) for m in models}
    eval_sets = [cut_segments(evaluate, replace(options.eval_segments(), horizon_m=h_e))
                 for h_e in h_e_values]
    for i, h_t in enumerate(h_t_values):
        # the main fit's segment options (interval included), at this horizon
        seg_opts = replace(options.train_segments(), horizon_m=h_t)
        train_seg = cut_segments(train, seg_opts)
        if len(train_seg) < 8:
            LOG.warning('h_t = %g m leaves %d training segments: skipped', h_t, len(train_seg))
            continue
        fits = fit_models_weighted(geometry, train_seg, options.fit_options(), models,
                                   options.weighting)
        for j, eval_seg in enumerate(eval_sets):
            if len(eval_seg) == 0:
                continue
            scores = evaluate_models({m: f.values for m, f in fits.items()}, geometry,
                                     eval_seg, options.min_eval_path_m)
            for m, ev in scores.items():
                median[m][i, j] = ev.stats_t.median
                iqr[m][i, j] = ev.stats_t.q75 - ev.stats_t.q25
    return HorizonStudy(tuple(h_t_values), tuple(h_e_values), median, iqr)
