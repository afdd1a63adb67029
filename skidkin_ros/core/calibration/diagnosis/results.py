"""What a diagnosis found: the before/after table, its text lines and the parameters file.

The result carries data only; the text lines for stdout (:meth:`DiagnosisResult.summary_lines`)
and the flat parameters (:meth:`DiagnosisResult.to_parameters`) are made from it here, the
Markdown report and figures in :mod:`skidkin_ros.report.diagnosis`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from skidkin_ros.core.calibration.diagnosis.interpret import Dependence, residual_dependence
from skidkin_ros.core.calibration.diagnosis.options import DiagnosisOptions
from skidkin_ros.core.calibration.diagnosis.select_extensions import CandidateScore
from skidkin_ros.core.calibration.diagnosis.state import ModelState
from skidkin_ros.core.calibration.diagnosis.tracing import ResidualLead, Trace
from skidkin_ros.core.calibration.engine import TwistSource
from skidkin_ros.core.calibration.evaluation import ErrorStats
from skidkin_ros.core.kinematics.augmented import AUGMENTED_NAME
from skidkin_ros.core.kinematics.extensions import get_extension
from skidkin_ros.core.kinematics.residual import INPUTS
from skidkin_ros.core.kinematics.specs import Geometry

__all__ = ['ModelStep', 'DiagnosisResult']


# What a lead that no wheel-state model can follow suggests.
_LEAD_HINTS = {
    'heading': "; it follows the speed times the world heading's sine and cosine, as a creep "
               'down a side slope does: no function of the wheel speeds can represent it',
}


@dataclass(frozen=True)
class ModelStep:
    """One model of the before/after table, with its held-out errors."""

    label: str
    state: ModelState
    eps_t: np.ndarray
    eps_theta_deg: np.ndarray
    stats_t: ErrorStats
    stats_theta: ErrorStats


@dataclass(frozen=True)
class DiagnosisResult:
    """What a diagnosis found (the report and the parameters file are made from it)."""

    base_model: str
    geometry: Geometry
    options: DiagnosisOptions
    trace: Trace
    candidates: tuple[CandidateScore, ...]
    steps: tuple[ModelStep, ...]
    final: ModelState
    residual_after: np.ndarray
    residual_valid: np.ndarray
    residual_after_valid: np.ndarray
    holdout: str = 'given'
    warnings: tuple[str, ...] = ()
    provenance: dict[str, Any] = field(default_factory=dict)
    unexplained: tuple[ResidualLead, ...] = ()

    @property
    def extensions(self) -> tuple[str, ...]:
        """Return the extensions the diagnosis found (the stamp convention is not one)."""
        return self.final.found

    @property
    def convention_s(self) -> float:
        return float(self.provenance.get('stamp_convention_s', 0.0))

    def bound(self) -> TwistSource:
        """Return the final (augmented) model, ready for the integrator."""
        return self.final.bind(self.base_model, self.geometry)

    def summary_lines(self) -> list[str]:
        """Return the findings and the before/after table as text lines (for stdout)."""
        lines = [f'diagnosis of {self.base_model} ({self.holdout})']
        lag = self.trace.lag_s
        if self.convention_s:
            lines.append(f'  wheel -> ground-truth lag (velocity refit): {lag * 1e3:+.0f} ms, '
                         f'beyond the stamp convention ({self.convention_s * 1e3:+.0f} ms: '
                         'speeds held from their stamp describe the middle of the interval)')
        else:
            lines.append(f'  wheel -> ground-truth lag (velocity refit): {lag * 1e3:+.0f} ms '
                         f'(interval {self.options.interval}: no stamp convention)')
        lines.append('  strongest residual correlations: ' + ', '.join(
            f'{c}~{s} r={r:+.2f}' for c, s, r in self.trace.top(4)))
        lines += [f'  {line}' for line in self.base_lines()]
        if not self.final.found:
            lines.append('  no extension added: no candidate passed the parsimony rule '
                         f'(held-out gain > {self.options.min_relative_gain:.0%} and p < '
                         f'{self.options.significance:g})')
        lines += [f'  {line}' for line in self.unexplained_lines()]
        for name in self.final.found:
            ext = get_extension(name)
            if ext.regression:
                lines += [f'  {line}' for line in self.residual_lines(name)]
                continue
            units = {spec.name: spec.unit for spec in ext.params}
            text = ', '.join(f'{k} = {v:.4g} {units.get(k, "")}'
                             for k, v in self.final.shown_values(name).items())
            lines.append(f'  added {name} ({ext.title}): {text}')
            notes = [c.note for c in self.candidates if c.accepted and c.name == name and c.note]
            lines += [f'    note: {note}' for note in notes]
        lines.append('  candidates (round, name, held-out gain, p, accepted):')
        for cand in self.candidates:
            terms = f' terms {list(cand.terms)}' if cand.terms else ''
            if len(cand.terms) > 8:
                terms = f' {len(cand.terms)} terms'
            if cand.note.startswith('screened out'):
                lines.append(f'    {cand.round_no} {cand.name:<20} {cand.note.split(",")[0]}')
                continue
            lines.append(f'    {cand.round_no} {cand.name:<20} {cand.relative_gain:+7.1%} '
                         f'p={cand.p_value:.2g} {"yes" if cand.accepted else "no"}{terms}')
        lines.append('  held-out errors: model | eps_t m/m median [q25, q75] p90 | '
                     'eps_theta deg/m median [q25, q75] p90 | segments')
        for step in self.steps:
            t, th = step.stats_t, step.stats_theta
            lines.append(f'    {step.label:<34} {t.median:.4f} [{t.q25:.4f}, {t.q75:.4f}] '
                         f'{t.p90:.4f} | {th.median:.3f} [{th.q25:.3f}, {th.q75:.3f}] '
                         f'{th.p90:.3f} | {t.count}')
        lines += [f'  warning: {w}' for w in self.warnings]
        return lines

    @property
    def given_base(self) -> str:
        return str(self.provenance.get('given_base_model', self.base_model))

    def base_lines(self) -> list[str]:
        """Return what questioning the base model found (nothing when it was not questioned)."""
        questioned = self.provenance.get('base_models_questioned', [])
        if not questioned:
            return []
        verdict = (f'{self.base_model} replaces {self.given_base}'
                   if self.base_model != self.given_base else f'{self.given_base} kept')
        return [f'base model questioned ({verdict}): ' + '; '.join(questioned)]

    def _regression(self) -> str | None:
        return next((n for n in self.final.found if get_extension(n).regression), None)

    def residual_dependence(self, name: str | None = None) -> tuple[Dependence, ...]:
        """Return what the residual model's correction follows (nothing when not found)."""
        name = name or self._regression()
        if name is None or name not in self.final.found:
            return ()
        return residual_dependence(self.final.ext_values[name], self.trace.signals,
                                   self.residual_valid)

    def residual_lines(self, name: str) -> list[str]:
        """Return the residual model's lines: what it follows, and the range it holds to."""
        ext = get_extension(name)
        values = self.final.ext_values[name]
        lines = [f'added {name} ({ext.title}, {len(self.final.terms(name))} terms, level '
                 f'{values.get("level", 0):.0f})']
        lines += [f'  {dep.text()}' for dep in self.residual_dependence(name)]
        ranges = ', '.join(f'{i} in [{values[i + "_lo"]:.3g}, {values[i + "_hi"]:.3g}] {unit}'
                           for i, unit, _ in INPUTS)
        lines.append(f'  fitted on {ranges}; outside that range the inputs are clamped to it (the '
                     'correction holds its edge value) and each change is bounded by the motion')
        return lines

    def unexplained_lines(self) -> list[str]:
        """Return one line per signal the final model's residual still follows."""
        return [f'unexplained residual: signal {lead.signal}, share {lead.share:.0%} of the '
                f'velocity error left (residual {lead.component} of the final model follows it, '
                f'r = {lead.r:+.2f}; no candidate explained it){_LEAD_HINTS.get(lead.signal, "")}'
                for lead in self.unexplained]

    def table_rows(self) -> list[list[str]]:
        """Return the before/after table rows (model, eps_t median/q25/q75/p90, eps_theta ...)."""
        rows = []
        for step in self.steps:
            t, th = step.stats_t, step.stats_theta
            rows.append([step.label] + [f'{v:.4f}' for v in (t.median, t.q25, t.q75, t.p90)]
                        + [f'{v:.3f}' for v in (th.median, th.q25, th.q75, th.p90)])
        return rows

    def to_parameters(self, base_flat: Mapping[str, Any]) -> dict[str, Any]:
        """Return complete flat parameters for ``config.write_params_file``.

        ``base_flat`` is the calibrated parameters file (flat, its provenance dropped: give
        ``self.provenance`` to write_params_file); the result keeps it and sets
        model = augmented, augmented.base, augmented.extensions and every extension value, and
        the base model's parameters as fitted jointly with the extensions. With no extension the
        base model is kept (model = base). ``interval`` is the convention diagnosed under.
        """
        flat = {k: v for k, v in base_flat.items() if not k.startswith('provenance.')}
        flat['interval'] = self.options.interval
        flat['wheel_radius'] = float(self.geometry.wheel_radius)
        flat['track_width'] = float(self.geometry.track_width)
        if not self.final.found:
            flat['model'] = self.base_model
            if self.base_model != self.given_base:  # the diagnosis replaced the base model
                for name, value in self.final.base_values.items():
                    flat[f'models.{self.base_model}.{name}'] = float(value)
            return flat
        for name, value in self.final.base_values.items():
            flat[f'models.{self.base_model}.{name}'] = float(value)
        flat['model'] = AUGMENTED_NAME
        flat['augmented.base'] = self.base_model
        flat['augmented.extensions'] = ', '.join(self.final.extensions)
        for name in self.final.extensions:
            for param, value in self.final.ext_values[name].items():
                flat[f'augmented.{name}.{param}'] = float(value)
        regression = self._regression()
        if self.final.residual_covariance and regression is not None:
            flat[f'augmented.{regression}.covariance'] = list(self.final.residual_covariance)
        return flat
