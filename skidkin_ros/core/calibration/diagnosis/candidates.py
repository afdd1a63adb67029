"""Fit one candidate: the current model plus one extension, on every fold of the training data.

1. **Folds.** Training segments are split into ``folds`` groups: by ``calib_step`` when every
   drive carries one, by drive when there are enough drives, else by interleaved time blocks of
   each drive (:func:`fold_labels`). Neighbouring segments share ground-truth noise, so a fold
   never mixes them with its training data more than it must.
2. **Start.** The extension joins the structure at the start values its registry entry gives
   from what the trace measured (``Extension.start_values(FitHints)``); a library extension's
   terms and start values come from STLSQ on the per-pose residuals of the fold's training
   drives, at the threshold of the variant (``sparse_correction@0.2``).
3. **Grid.** Step-like parameters (``Extension.scan``, e.g. a terrain switch time) are searched
   on a coarse grid over ``Extension.scan_range(hints)``, then a fine grid around the best; each
   value is scored by a short fit of the extension's other parameters, the base fixed.
4. **Fit.** :func:`~skidkin_ros.core.calibration.diagnosis.state.fit_state` with the base
   refitted jointly; grid-searched parameters the extension does not refine stay fixed.
5. **Task.** One unit of cross-validation is (state, candidate, fold): fitted without the fold
   and scored on it (per-segment held-out losses), or, for fold None, fitted on all training
   segments (the state kept if the candidate is accepted). Tasks are independent: the selection
   runs them on several processes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import time
from typing import Any, Callable, Sequence

import numpy as np

from skidkin_ros.core.calibration.diagnosis.options import DiagnosisOptions
from skidkin_ros.core.calibration.diagnosis.regression import fit_residual_model
from skidkin_ros.core.calibration.diagnosis.residuals import PoseSamples
from skidkin_ros.core.calibration.diagnosis.sparse import library_start
from skidkin_ros.core.calibration.diagnosis.state import fit_state, held_out_loss, ModelState
from skidkin_ros.core.calibration.predictor import SegmentPredictor
from skidkin_ros.core.calibration.segments import SegmentSet
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.kinematics.extensions import FitHints, get_extension, ordered
from skidkin_ros.core.kinematics.specs import Geometry

__all__ = ['CandidateFitter', 'Task', 'fold_labels', 'split_variant', 'variant_name']

# Least-squares iterations (per parameter) of each grid point's short fit.
SCAN_MAX_NFEV = 10
# (state, candidate or None for the current model alone, fold or None for all segments)
Task = tuple[ModelState, 'str | None', 'int | None']


def fold_labels(drives: Sequence[Drive], segments: SegmentSet, folds: int) -> np.ndarray:
    """Assign each segment to a fold: by calib_step, by drive, or interleaved time blocks."""
    count = len(segments)
    if count == 0:
        return np.zeros(0, dtype=int)
    steps = [d.meta.get('calib_step') for d in drives]
    if all(s is not None for s in steps):
        keys = np.array([int(steps[d]) for d in segments.drive])
        _, groups = np.unique(keys, return_inverse=True)
        return groups % folds
    if len(drives) >= 2 * folds:
        return segments.drive % folds
    labels = np.zeros(count, dtype=int)
    blocks = 3 * folds
    for d in np.unique(segments.drive):
        rows = np.nonzero(segments.drive == d)[0]
        order = rows[np.argsort(segments.t_a_ns[rows], kind='stable')]
        block = (np.arange(order.size) * blocks) // max(order.size, 1)
        labels[order] = block % folds
    return labels


def variant_name(extension: str, threshold: float) -> str:
    """Return the candidate name of a library extension at one STLSQ threshold."""
    return f'{extension}@{threshold:g}'


def split_variant(name: str | None) -> tuple[str | None, float | None]:
    """Split a candidate name into (extension, STLSQ threshold or None)."""
    if name is None or '@' not in name:
        return name, None
    ext, _, threshold = name.partition('@')
    return ext, float(threshold)


@dataclass(frozen=True)
class _Trial:
    """One grid value of a scanned parameter and the short fit at it."""

    cost: float
    value: float
    state: ModelState


class CandidateFitter:
    """Fits the current model plus a candidate on the training segments (module docstring)."""

    def __init__(self, drives: Sequence[Drive], segments: SegmentSet, base_name: str,
                 geometry: Geometry, options: DiagnosisOptions, samples: PoseSamples,
                 hints: FitHints) -> None:
        self.drives = drives
        self.predictor = SegmentPredictor(drives, segments, options.max_dt_s,
                                          options.interval)
        self.base_name = base_name
        self.geometry = geometry
        self.options = options
        self.samples = samples
        self.hints = hints
        self.labels = fold_labels(drives, segments, options.folds)
        self._scan_options = replace(options, max_nfev=SCAN_MAX_NFEV)

    def with_extension(self, state: ModelState, name: str, keep: np.ndarray | None = None,
                       threshold: float | None = None) -> ModelState:
        """Return the state plus the extension at its start values (step 2).

        ``threshold``: a library extension's STLSQ threshold (default: the smallest of the
        options').
        """
        ext = get_extension(name)
        values = dict(state.ext_values)
        terms = state.sparse_terms
        covariance = state.residual_covariance
        if ext.library:
            values[name], terms = self._library_start(state, keep, threshold)
        elif ext.regression:
            fit = fit_residual_model(self.drives, self.samples,
                                     state.bind(self.base_name, self.geometry), self.options,
                                     self._pose_mask(keep))
            values[name], covariance = fit.values, fit.covariance
        else:
            values[name] = ext.start_values(self.hints)
        structure = state.extensions if name in state.extensions else state.extensions + (name,)
        state = ModelState(ordered(structure), dict(state.base_values), values, terms,
                           state.found + (name,), covariance)
        return state

    def _pose_mask(self, keep: np.ndarray | None) -> np.ndarray | None:
        """Return the poses inside the kept segments' windows (None: every pose)."""
        if keep is None:
            return None
        seg = self.predictor.segments
        mask = np.zeros(self.samples.t_ns.size, dtype=bool)
        for d in np.unique(seg.drive[keep]):
            rows = keep[seg.drive[keep] == d]
            lo = np.sort(seg.t_a_ns[rows].astype(np.int64))
            hi = np.sort(seg.t_b_ns[rows].astype(np.int64))
            mine = np.nonzero(self.samples.drive == d)[0]
            t = self.samples.t_ns[mine].astype(np.int64)
            # inside some [t_a, t_b]: more windows started than ended before t
            started = np.searchsorted(lo, t, side='right')
            ended = np.searchsorted(hi, t, side='left')
            mask[mine] = started > ended
        return mask

    def _library_start(self, state: ModelState, keep: np.ndarray | None,
                       threshold: float | None) -> tuple[dict[str, float], tuple[str, ...]]:
        if threshold is None:
            threshold = min(self.options.sparse_thresholds)
        drives_kept = None if keep is None else np.unique(self.predictor.segments.drive[keep])
        return library_start(self.drives, self.samples, state.bind(self.base_name, self.geometry),
                             self.options, drives_kept, threshold)

    def fit(self, state: ModelState, keep: np.ndarray | None = None,
            scan: str | None = None) -> ModelState:
        """Fit a structure on the (kept) segments (steps 3 and 4).

        The step-like parameters of the extension ``scan`` are grid-searched first (those of
        the other extensions keep the values they have).
        """
        if scan is not None:
            for param in get_extension(scan).scan:
                state = self._scan(state, scan, param, keep)
        fixed = [f'{n}.{p}' for n in state.extensions for p in get_extension(n).scan
                 if not get_extension(n).refine]
        # A regression extension is fitted in closed form on the current model's residual:
        # refitting the base under it would move what it was fitted against.
        refit = None if scan is None or not get_extension(scan).regression else False
        fitted, _ = fit_state(self.predictor, self.base_name, self.geometry, state, self.options,
                              keep, refit_base=refit, fixed=fixed)
        return fitted

    def _trial(self, state: ModelState, name: str, param: str, value: float,
               keep: np.ndarray | None) -> _Trial:
        values = {k: dict(v) for k, v in state.ext_values.items()}
        values[name][param] = float(value)
        trial = ModelState(state.extensions, state.base_values, values, state.sparse_terms,
                           state.found, state.residual_covariance)
        fitted, cost = fit_state(self.predictor, self.base_name, self.geometry, trial,
                                 self._scan_options, keep, refit_base=False,
                                 fixed=(f'{name}.{param}',))
        return _Trial(cost, value, fitted)

    def _scan(self, state: ModelState, name: str, param: str,
              keep: np.ndarray | None) -> ModelState:
        """Search a coarse grid over the extension's scan range, then a fine grid at the best."""
        low, high = get_extension(name).scan_range(self.hints)
        count = self.options.scan_points
        grid = low + np.linspace(0.05, 0.95, count) * (high - low)
        best = min((self._trial(state, name, param, v, keep) for v in grid),
                   key=lambda trial: trial.cost)
        step = grid[1] - grid[0] if count > 1 else high - low
        fine = best.value + np.linspace(-step, step, count)
        fine = fine[(fine > low) & (fine < high)]
        trials = [best] + [self._trial(state, name, param, v, keep) for v in fine]
        return min(trials, key=lambda trial: trial.cost).state

    def prepare(self, name: str | None) -> Callable[[ModelState, np.ndarray | None], ModelState]:
        """Return a function (state, keep) -> fitted state for the CV of one candidate.

        ``name``: an extension, a library variant (``sparse_correction@THRESHOLD``), or None
        for the current model alone.
        """
        ext, threshold = split_variant(name)

        def run(state: ModelState, keep: np.ndarray | None) -> ModelState:
            if ext is not None:
                state = self.with_extension(state, ext, keep, threshold)
            return self.fit(state, keep, scan=ext)
        return run

    def task(self, task: Task) -> tuple[Any, float]:
        """Run one unit of the selection (step 5); return (its value, seconds).

        The value is the fold's per-segment held-out losses (None when the fold or the rest is
        empty), or for fold None the candidate's state fitted on all training segments.
        """
        tic = time.perf_counter()
        state, name, fold = task
        if fold is None:
            value: Any = self.prepare(name)(state, None)
        else:
            test = np.nonzero(self.labels == fold)[0]
            train = np.nonzero(self.labels != fold)[0]
            value = None
            if test.size and train.size:
                fitted = self.prepare(name)(state, train)
                value = held_out_loss(self.predictor, fitted.bind(self.base_name, self.geometry),
                                      self.options, test)
        return value, time.perf_counter() - tic
