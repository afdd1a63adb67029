"""Choose what to add: forward selection in rounds, with a parsimony rule on held-out error.

Each round, as a recipe:

1. **Score.** Every candidate not yet found is fitted on all training segments; those that
   lower the training loss by more than ``SCREEN_FRACTION`` of ``min_relative_gain`` are then
   fitted on each fold's complement and scored on the fold (:mod:`.candidates`), the current model
   alone too, in the first group of the round (the others are screened out, and said so).
   Named extensions go first; the library extensions (the sparse fallback) only when no named
   one passes, at every STLSQ threshold of ``sparse_thresholds``, and the variant with the
   fewest terms whose held-out loss is not significantly above the best one's is the one scored
   (:func:`sparsest`).
2. **Parsimony.** A candidate passes when it lowers the summed held-out loss by more than
   ``min_relative_gain`` AND a one-sided Wilcoxon signed-rank test of the per-segment
   differences gives p < ``significance``.
3. **Pick.** The passing candidate with the best gain, unless a simpler passing one is not
   significantly worse (``Extension.complexity``: fewer parameters, then no state), or the best
   is an extension that cannot be told from a simpler one at this wheel sample period
   (``Extension.short_alias``: a first-order lag no longer than one sample is a delay).
4. **Repeat** from the picked model, at most ``max_extensions`` rounds; stop when none passes.
   An extension of a ``group`` already in the model (a second lag) is not a candidate.

The fits of a round are independent tasks run on ``jobs`` processes
(:func:`skidkin_ros.core.parallel.fork_map`); the result does not depend on their number.
"""

from __future__ import annotations

from dataclasses import dataclass
import logging
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy import stats

from skidkin_ros.core.calibration.diagnosis.candidates import (CandidateFitter, split_variant,
                                                               Task, variant_name)
from skidkin_ros.core.calibration.diagnosis.state import held_out_loss, ModelState
from skidkin_ros.core.kinematics.extensions import get_extension
from skidkin_ros.core.parallel import fork_map

__all__ = ['CandidateScore', 'Outcome', 'RoundScore', 'Progress', 'p_greater', 'significance',
           'sparsest', 'pick', 'select']

LOG = logging.getLogger(__name__)
# Two passing candidates whose held-out losses differ with p >= this are called a tie.
TIE_SIGNIFICANCE = 0.05
# A candidate is cross-validated only when its training-loss gain exceeds this fraction of
# min_relative_gain (step 1, screening).
SCREEN_FRACTION = 0.5
# progress(round, fits done, fits in the round): how a caller follows a long selection.
Progress = Callable[[int, int, int], None]


@dataclass(frozen=True)
class CandidateScore:
    """One candidate in one round of the forward selection (what the report lists)."""

    round_no: int
    name: str
    relative_gain: float
    p_value: float
    accepted: bool
    values: dict[str, float]
    terms: tuple[str, ...] = ()
    seconds: float = 0.0  # fitting time, summed over its tasks (which may run in parallel)
    note: str = ''


@dataclass(frozen=True)
class Outcome:
    """A candidate's cross-validation: per-segment held-out losses, state fitted on all data.

    ``seconds``: fitting time summed over its tasks.
    """

    losses: np.ndarray
    state: ModelState
    seconds: float


@dataclass(frozen=True)
class RoundScore:
    """A candidate's outcome judged against the current model (steps 2 and 3)."""

    name: str
    outcome: Outcome
    gain: float
    p_value: float
    passes: bool

    @property
    def complexity(self) -> tuple[int, int]:
        return get_extension(self.name).complexity(self.outcome.state.terms(self.name))


def p_greater(diff: np.ndarray, untestable: float) -> float:
    """Return the one-sided Wilcoxon p-value that ``diff`` is above 0.

    ``untestable`` is returned when fewer than 5 differences are non-zero or the test fails.
    """
    if np.count_nonzero(diff) < 5:
        return untestable
    try:
        return float(stats.wilcoxon(diff, alternative='greater').pvalue)
    except ValueError:
        return untestable


def significance(null: np.ndarray, cand: np.ndarray) -> tuple[float, float]:
    """Return (relative held-out gain, p-value that the candidate's losses are lower)."""
    total = float(null.sum())
    gain = 1.0 - float(cand.sum()) / total if total > 0 else 0.0
    return gain, p_greater(null - cand, untestable=1.0)


def sparsest(outcomes: Mapping[str, Outcome]) -> tuple[Outcome, str]:
    """Keep the library variant with the fewest terms among those as good as the best.

    ``outcomes``: variant name -> outcome, all variants of one library extension. A variant is
    as good as the one with the lowest total held-out loss unless a one-sided Wilcoxon test says
    its per-segment losses are higher (p < TIE_SIGNIFICANCE). Returns the kept outcome (its
    seconds: all variants') and a note naming the threshold kept.
    """
    best = min(outcomes, key=lambda n: outcomes[n].losses.sum())
    as_good = []
    for name, outcome in outcomes.items():
        p_value = (1.0 if name == best
                   else p_greater(outcome.losses - outcomes[best].losses, untestable=1.0))
        if p_value >= TIE_SIGNIFICANCE:
            as_good.append((len(outcome.state.sparse_terms), -split_variant(name)[1], name))
    kept = outcomes[min(as_good)[2]]
    seconds = sum(outcome.seconds for outcome in outcomes.values())
    counts = ', '.join(f'{split_variant(n)[1]:g}: {len(o.state.sparse_terms)}'
                       for n, o in outcomes.items())
    note = (f'STLSQ threshold {split_variant(min(as_good)[2])[1]:g} kept (terms by threshold: '
            f'{counts}); the fewest terms whose held-out loss is not significantly above the best')
    return Outcome(kept.losses, kept.state, seconds), note


def pick(scores: Sequence[RoundScore], period_s: float
         ) -> tuple[RoundScore | None, list[str]]:
    """Return the accepted candidate of a round and the passing ones it could not be told from.

    The best held-out gain wins, unless a simpler passing candidate is not significantly worse
    (one-sided Wilcoxon on the per-segment held-out losses, p >= TIE_SIGNIFICANCE): a small
    time offset and a short first-order lag, for instance, fit a drive almost equally well.
    An extension with a ``short_alias`` (parameter, other) whose parameter is no longer than one
    wheel sample period cannot be told from the other when the speeds are held between stamps:
    the other is kept then, when it passes too.
    """
    winners = [score for score in scores if score.passes]
    if not winners:
        return None, []
    best = max(winners, key=lambda score: score.gain)
    alias = get_extension(best.name).short_alias
    if alias is not None:
        param, other = alias
        simpler = [score for score in winners if score.name == other]
        if simpler and best.outcome.state.ext_values[best.name][param] <= period_s:
            return simpler[0], [best.name]
    tied = [score for score in winners if score is not best and p_greater(
        score.outcome.losses - best.outcome.losses, untestable=0.0) >= TIE_SIGNIFICANCE]
    if not tied:
        return best, []
    group = [best] + tied
    chosen = min(group, key=lambda score: (score.complexity, -score.gain))
    return chosen, [score.name for score in group if score is not chosen]


class _Rounds:
    """Runs the rounds of the selection over one candidate fitter."""

    def __init__(self, fitter: CandidateFitter, jobs: int, progress: Progress | None) -> None:
        self.fitter = fitter
        self.options = fitter.options
        self.jobs = jobs
        self.progress = progress
        self.folds = tuple(range(self.options.folds))
        self.training_gain: dict[str, float] = {}
        self.training_loss: dict[str, float] = {}  # of the last group's candidates

    def held_out(self, values: Mapping[int, Any]) -> np.ndarray:
        """Assemble the per-segment held-out losses from the fold results."""
        losses = np.zeros(len(self.fitter.predictor))
        for fold, value in values.items():
            if value is not None:
                losses[self.fitter.labels == fold] = value
        return losses

    def _fork(self, state: ModelState, keys: Sequence[tuple[str | None, int | None]],
              round_index: int) -> dict[tuple[str | None, int | None], tuple[Any, float]]:
        """Run the tasks ``keys``; a candidate's training loss is taken in its worker too."""
        progress = self.progress
        on_done = (None if progress is None
                   else lambda done, total: progress(round_index, done, total))
        tasks: list[Task] = [(state, name, fold) for name, fold in keys]
        results = {}
        for key, (value, seconds, loss) in zip(keys, fork_map(self._task, tasks, self.jobs,
                                                              on_done)):
            results[key] = (value, seconds)
            if loss is not None:
                self.training_loss[key[0]] = loss
        return results

    def _task(self, task: Task) -> tuple[Any, float, float | None]:
        """Run one task; a candidate fitted on all segments also gets its training loss."""
        value, seconds = self.fitter.task(task)
        _, name, fold = task
        loss = self._training_loss(value) if fold is None and name is not None else None
        return value, seconds, loss

    def _training_loss(self, state: ModelState) -> float:
        fitter = self.fitter
        return float(held_out_loss(fitter.predictor, state.bind(fitter.base_name,
                                                                fitter.geometry),
                                   self.options).sum())

    def run(self, state: ModelState, names: Sequence[str], with_null: bool,
            round_index: int) -> dict[tuple[str | None, int | None], tuple[Any, float]]:
        """Run every task of a group (on ``jobs`` cores); results keyed by (name, fold).

        Screening (step 1): every candidate is first fitted on all training segments; only those
        that lower the training loss by more than ``SCREEN_FRACTION`` of the required held-out
        gain are cross-validated (a candidate that does not fit the data it was fitted on cannot
        generalise better). The others get no fold results; :meth:`outcome` notes why.
        """
        # The grid-searched candidates are the longest: started first, they finish with the rest;
        # the current model's folds need no screening and fill the gaps at the end.
        by_cost = sorted(names, key=lambda n: not get_extension(split_variant(n)[0]).scan)
        keys = [(name, None) for name in by_cost]
        keys += [(None, fold) for fold in self.folds] if with_null else []
        results = self._fork(state, keys, round_index)
        null_loss = self._training_loss(state)
        for name in by_cost:
            loss = self.training_loss[name]
            self.training_gain[name] = 1.0 - loss / null_loss if null_loss > 0 else 0.0
        threshold = SCREEN_FRACTION * self.options.min_relative_gain
        promising = [n for n in by_cost if self.training_gain[n] > threshold]
        keys = [(name, fold) for name in promising for fold in self.folds]
        results.update(self._fork(state, keys, round_index))
        return results

    def outcome(self, results: Mapping, name: str, null: np.ndarray) -> Outcome:
        full, seconds = results[name, None]
        if (name, self.folds[0]) not in results:  # screened out: scored as the current model
            return Outcome(null.copy(), full, seconds)
        losses = self.held_out({f: results[name, f][0] for f in self.folds})
        return Outcome(losses, full, seconds + sum(results[name, f][1] for f in self.folds))

    def score_round(self, current: ModelState, round_index: int
                    ) -> tuple[list[RoundScore], dict[str, str]]:
        """Score the candidates of one round (steps 1 and 2); return scores and notes."""
        options = self.options
        taken = {get_extension(n).group for n in current.extensions} - {''}
        pool = [n for n in options.candidates
                if n not in current.found and get_extension(n).group not in taken]
        named = [n for n in pool if not get_extension(n).learned]
        library = [n for n in pool if get_extension(n).library]
        thresholds = sorted(set(options.sparse_thresholds))
        variants = [n for n in pool if get_extension(n).regression]
        variants += [variant_name(n, t) for n in library for t in thresholds]
        scores: list[RoundScore] = []
        notes: dict[str, str] = {}
        null = None
        for group in (named, variants):
            if not group:
                continue
            results = self.run(current, group, null is None, round_index)
            if null is None:
                null = self.held_out({f: results[None, f][0] for f in self.folds})
            outcomes = {name: self.outcome(results, name, null) for name in group}
            for name in group:
                if (name, self.folds[0]) not in results:
                    notes[split_variant(name)[0] if '@' in name else name] = (
                        f'screened out: training-loss gain {self.training_gain[name]:+.1%} <= '
                        f'{SCREEN_FRACTION * options.min_relative_gain:.1%}, not '
                        'cross-validated')
            if group is variants:
                outcomes = {**{n: o for n, o in outcomes.items() if n in pool},
                            **self._sparsest_each(library, outcomes, notes)}
            for name, outcome in outcomes.items():
                gain, p_value = significance(null, outcome.losses)
                passes = gain > options.min_relative_gain and p_value < options.significance
                scores.append(RoundScore(name, outcome, gain, p_value, passes))
                LOG.info('round %d %s: held-out gain %.3f p %.3g', round_index, name, gain,
                         p_value)
            if any(score.passes for score in scores):
                break
        return scores, notes

    @staticmethod
    def _sparsest_each(library: Sequence[str], outcomes: Mapping[str, Outcome],
                       notes: dict[str, str]) -> dict[str, Outcome]:
        kept = {}
        for name in library:
            mine = {v: o for v, o in outcomes.items() if split_variant(v)[0] == name}
            kept[name], notes[name] = sparsest(mine)
        return kept


def _candidate_score(round_index: int, score: RoundScore, chosen: bool, tied: Sequence[str],
                     notes: Mapping[str, str]) -> CandidateScore:
    state = score.outcome.state
    learned = get_extension(score.name).learned
    terms = state.terms(score.name) if learned else ()
    values = dict(state.ext_values.get(score.name, {}))
    if learned:
        values = {t: values[t] for t in terms}
    note = (f'indistinguishable from {", ".join(tied)} on this data; the simpler '
            'explanation is kept' if chosen and tied else '')
    note = '; '.join(part for part in (notes.get(score.name, ''), note) if part)
    return CandidateScore(round_index, score.name, score.gain, score.p_value, chosen, values,
                          terms, score.outcome.seconds, note)


def select(fitter: CandidateFitter, start: ModelState, jobs: int = 1,
           progress: Progress | None = None
           ) -> tuple[ModelState, list[CandidateScore], list[ModelState]]:
    """Run the rounds (module docstring) from ``start``.

    Returns the final state, every candidate's score, and the state after each accepted round.
    """
    rounds = _Rounds(fitter, jobs, progress)
    current = start
    scores: list[CandidateScore] = []
    accepted: list[ModelState] = []
    for round_index in range(1, fitter.options.max_extensions + 1):
        round_scores, notes = rounds.score_round(current, round_index)
        best, tied = pick(round_scores, fitter.hints.period_s)
        for score in round_scores:
            chosen = best is not None and score.name == best.name
            scores.append(_candidate_score(round_index, score, chosen, tied, notes))
        if best is None:
            break
        current = best.outcome.state
        accepted.append(current)
    return current, scores, accepted
