"""Question the base model: is another of the five (asymmetry, ICR offsets, ROC) better.

A calibration may keep a simpler model within two standard errors (``edd_symmetric`` for an
asymmetric robot); the diagnosis then builds on the wrong base, and an extension has to stand in
for the asymmetry. Before the extensions, as a recipe:

1. **Candidates.** Every other model with parameters, started from the values the parameters
   file holds for it (its calibrated values) or its defaults.
2. **Cross-validation.** Each is fitted on each fold's complement of the training segments and
   scored on the fold (the folds of :func:`~.candidates.fold_labels`), as the extensions are;
   the given model too.
3. **Parsimony.** A model replaces the given one when it lowers the summed held-out loss by more
   than ``min_relative_gain`` with a one-sided Wilcoxon p < ``significance`` (the extensions'
   rule); among passing models, the one with the best gain, unless one with fewer parameters is
   not significantly worse. The recipe then keeps it only if, with the extensions found on it,
   it ends with a lower held-out loss than the given model with its own
   (:func:`.recipe.diagnose`).

The fits run on ``jobs`` processes. The result lists every model's gain and p-value.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from skidkin_ros.core.calibration.diagnosis.candidates import fold_labels
from skidkin_ros.core.calibration.diagnosis.options import DiagnosisOptions
from skidkin_ros.core.calibration.diagnosis.select_extensions import p_greater, significance, \
    TIE_SIGNIFICANCE
from skidkin_ros.core.calibration.diagnosis.state import fit_state, held_out_loss, ModelState
from skidkin_ros.core.calibration.predictor import SegmentPredictor
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.kinematics.models import get_model, MODEL_NAMES
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.parallel import fork_map

__all__ = ['BaseScore', 'question_base']


@dataclass(frozen=True)
class BaseScore:
    """One base model against the given one: held-out gain, p-value, whether it replaced it."""

    name: str
    gain: float
    p_value: float
    passes: bool
    accepted: bool
    values: dict[str, float]
    note: str = ''


class _BaseFits:
    def __init__(self, predictor: SegmentPredictor, labels: np.ndarray, geometry: Geometry,
                 options: DiagnosisOptions, starts: Mapping[str, Mapping[str, float]]) -> None:
        self.predictor = predictor
        self.labels = labels
        self.geometry = geometry
        self.options = options
        self.starts = starts

    def task(self, task: tuple[str, int | None]):
        name, fold = task
        state = ModelState((), dict(self.starts.get(name, {})), {})
        if fold is None:
            fitted, _ = fit_state(self.predictor, name, self.geometry, state, self.options,
                                  refit_base=True)
            return fitted
        test = np.nonzero(self.labels == fold)[0]
        train = np.nonzero(self.labels != fold)[0]
        if not (test.size and train.size):
            return None
        fitted, _ = fit_state(self.predictor, name, self.geometry, state, self.options, train,
                              refit_base=True)
        return held_out_loss(self.predictor, fitted.bind(name, self.geometry), self.options,
                             test)


def question_base(drives: Sequence[Drive], predictor: SegmentPredictor, geometry: Geometry,
                  given: str, starts: Mapping[str, Mapping[str, float]],
                  options: DiagnosisOptions, jobs: int = 1
                  ) -> tuple[str, ModelState | None, tuple[BaseScore, ...]]:
    """Return (the base model to build on, its state fitted on all segments or None, scores)."""
    names = [n for n in MODEL_NAMES if n != given and get_model(n).params]
    labels = fold_labels(drives, predictor.segments, options.folds)
    fits = _BaseFits(predictor, labels, geometry, options, starts)
    folds = tuple(range(options.folds))
    keys = [(n, f) for n in [given] + names for f in folds] + [(n, None) for n in names]
    values = dict(zip(keys, fork_map(fits.task, keys, jobs)))

    def losses(name: str) -> np.ndarray:
        out = np.zeros(len(predictor))
        for fold in folds:
            if values[name, fold] is not None:
                out[labels == fold] = values[name, fold]
        return out

    null = losses(given)
    scored = []
    for name in names:
        cand = losses(name)
        gain, p_value = significance(null, cand)
        passes = gain > options.min_relative_gain and p_value < options.significance
        scored.append((name, cand, gain, p_value, passes))
    winners = [s for s in scored if s[4]]
    chosen = None
    if winners:
        best = max(winners, key=lambda s: s[2])
        tied = [s for s in winners if s is best or p_greater(s[1] - best[1], 0.0)
                >= TIE_SIGNIFICANCE]
        chosen = min(tied, key=lambda s: (len(get_model(s[0]).params), -s[2]))[0]
    scores = tuple(BaseScore(name, gain, p_value, passes, name == chosen,
                             dict(values[name, None].base_values))
                   for name, _, gain, p_value, passes in scored)
    if chosen is None:
        return given, None, scores
    return chosen, values[chosen, None], scores
