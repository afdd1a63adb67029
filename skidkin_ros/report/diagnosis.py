"""The diagnosis report: residual-versus-signal figures before and after, and a Markdown page."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from skidkin_ros.atomic import atomic_write_text  # noqa: E402
from skidkin_ros.core.calibration.diagnosis import COMPONENTS, DiagnosisResult  # noqa: E402
from skidkin_ros.core.calibration.diagnosis.interpret import (  # noqa: E402
    residual_correction_at)
from skidkin_ros.core.kinematics.extensions import (get_extension, LIBRARY,  # noqa: E402
                                                    sparse_features)
from skidkin_ros.report.figures import save_figure  # noqa: E402
from skidkin_ros.report.page import (figure_lines, prepare_report,  # noqa: E402
                                     provenance_lines)

__all__ = ['residual_figure', 'error_figure', 'render_diagnosis_page', 'write_diagnosis_report']

_SIGN_SOURCE = {'v_x': 'body_speed', 'omega': 'yaw_rate'}
_OUTPUT_COMPONENT = {'vx': 'v_x', 'vy': 'v_y', 'wz': 'omega'}


def _main_library_term(result: DiagnosisResult, name: str) -> tuple[str, str]:
    """Return (component, signal) of the library term that moves the twist the most."""
    signals = result.trace.signals
    twist = np.stack([signals['body_speed'], np.zeros_like(signals['body_speed']),
                      signals['yaw_rate']], axis=-1)
    zero = np.zeros_like(signals['body_speed'])
    rate = np.stack([signals.get('d_body_speed', zero), zero, signals.get('d_yaw_rate', zero)],
                    axis=-1)
    spread = dict(zip((term.name for term in LIBRARY),
                      sparse_features(twist, rate).std(axis=0)))
    signal_of = {term.name: term.signal for term in LIBRARY}
    values = result.final.ext_values.get(name, {})
    best = max(result.final.sparse_terms,
               key=lambda term: abs(values.get(term, 0.0)) * spread[term.split('_', 1)[1]])
    output, feature = best.split('_', 1)
    return _OUTPUT_COMPONENT[output], signal_of[feature]


def _binned(x: np.ndarray, y: np.ndarray, bins: int = 20) -> tuple[np.ndarray, np.ndarray]:
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < bins:
        return np.zeros(0), np.zeros(0)
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
    which = np.clip(np.searchsorted(edges, x, side='right') - 1, 0, edges.size - 2)
    centres, means = [], []
    for b in range(edges.size - 1):
        sel = which == b
        if sel.sum() >= 3:
            centres.append(float(np.median(x[sel])))
            means.append(float(np.mean(y[sel])))
    return np.array(centres), np.array(means)


def _explained(result: DiagnosisResult) -> list[tuple[str, str, str, bool]]:
    """Return (title, component, signal, fold) for each found extension (or the top signal)."""
    items = []
    for name in result.extensions:
        ext = get_extension(name)
        component, signal, fold = ext.residual_view
        if ext.library and result.final.sparse_terms:
            component, signal = _main_library_term(result, name)
        if ext.regression:
            deps = result.residual_dependence(name)
            if deps:
                component, signal, fold = deps[0].component, deps[0].signal, False
        items.append((name, component, signal, fold))
    if not items:
        top = result.trace.top(1)
        if top:
            items.append(('strongest correlation (no extension added)', top[0][0], top[0][1],
                          False))
    return items


def residual_figure(result: DiagnosisResult, path: Path) -> Path:
    """Plot the residual against the signal that explains each found effect, before and after."""
    items = _explained(result)
    count = max(len(items), 1)
    fig, axes = plt.subplots(1, count, figsize=(5.0 * count, 4.0), squeeze=False)
    signals = result.trace.signals
    for ax, (title, component, signal, fold) in zip(axes[0], items):
        c = COMPONENTS.index(component)
        x = signals.get(signal)
        if x is None:
            ax.set_title(f'{title}: signal {signal} not in the data')
            continue
        before = result.trace.residual[:, c]
        after = result.residual_after[:, c]
        if fold:
            sign = np.sign(signals[_SIGN_SOURCE[component]])
            before, after = before * sign, after * sign
        valid_b, valid_a = result.residual_valid, result.residual_after_valid
        ax.scatter(x[valid_b], before[valid_b], s=3, alpha=0.25, color='tab:red',
                   label='before (base model)')
        ax.scatter(x[valid_a], after[valid_a], s=3, alpha=0.25, color='tab:blue',
                   label='after (augmented)')
        for values, valid, color in ((before, valid_b, 'darkred'), (after, valid_a, 'navy')):
            cx, cy = _binned(x[valid], values[valid])
            ax.plot(cx, cy, color=color, linewidth=2)
        if title in result.final.found and get_extension(title).regression:
            # the slice: the learned correction against the signal that explains most
            learned = residual_correction_at(result.final.ext_values[title], signals)[:, c]
            cx, cy = _binned(x[valid_b], learned[valid_b])
            ax.plot(cx, cy, color='tab:green', linewidth=2.5, linestyle='--',
                    label='learned correction')
        ax.axhline(0.0, color='black', linewidth=0.8)
        spread = np.percentile(np.abs(before[valid_b]), 99) if valid_b.any() else 0.0
        if spread > 0:
            ax.set_ylim(-1.3 * spread, 1.3 * spread)
        unit = 'rad/s' if component == 'omega' else 'm/s'
        ax.set_xlabel(signal)
        ax.set_ylabel(f'residual {component} ({unit})' + (' x direction' if fold else ''))
        ax.set_title(title)
        ax.legend(loc='best', fontsize=8, markerscale=3)
    return save_figure(fig, path)


def error_figure(result: DiagnosisResult, path: Path) -> Path:
    """Box plots of held-out eps_t and eps_theta for each model of the before/after table."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    labels = [step.label for step in result.steps]
    for ax, attr, title in ((axes[0], 'eps_t', 'eps_t (m/m)'),
                            (axes[1], 'eps_theta_deg', 'eps_theta (deg/m)')):
        data = [getattr(step, attr) for step in result.steps]
        shown = [i for i, d in enumerate(data) if d.size]
        if shown:
            ax.boxplot([data[i] for i in shown], positions=shown, showfliers=False)
        ax.set_xticks(range(len(labels)))
        ax.set_xticklabels(labels, rotation=20, ha='right', fontsize=8)
        ax.set_title(f'held-out {title}')
    return save_figure(fig, path)


def _num(value: float, digits: int = 4) -> str:
    return '–' if value is None or not math.isfinite(value) else f'{value:.{digits}g}'


def render_diagnosis_page(result: DiagnosisResult, images: dict[str, str]) -> str:
    """Return the Markdown text of the diagnosis report."""
    found = result.extensions
    lines = ['# skidkin_ros diagnosis report', '',
             f'Base model `{result.base_model}`, r = {result.geometry.wheel_radius:g} m, '
             f'b = {result.geometry.track_width:g} m; evaluation data: {result.holdout}.', '']
    if found:
        lines.append('**Found:** ' + ', '.join(f'`{name}`' for name in found) + '.')
    else:
        lines.append('**No extension added**: no candidate lowered the cross-validated error by '
                     f'more than {result.options.min_relative_gain:.0%} with p < '
                     f'{result.options.significance:g}.')
    lines += ['', '## Findings', '']
    for line in result.summary_lines()[1:3]:
        lines.append('- ' + line.strip())
    lines += [f'- **{line}**' for line in result.unexplained_lines()]
    for name in found:
        ext = get_extension(name)
        if ext.regression:
            lines += ['- ' + result.residual_lines(name)[0]]
            lines += [f'  - {line.strip()}' for line in result.residual_lines(name)[1:]]
            continue
        lines.append(f'- `{name}` ({ext.title}; {ext.formula}): ' + ', '.join(
            f'{p} = {_num(v)}' for p, v in result.final.shown_values(name).items()))
    lines += ['', '## Held-out errors, before and after', '',
              '| model | eps_t median | q25 | q75 | p90 | eps_theta median (deg/m) | q25 | q75 '
              '| p90 |', '|' + '---|' * 9]
    lines += ['| ' + ' | '.join(row) + ' |' for row in result.table_rows()]
    lines += ['', '## Candidates (cross-validated on the training segments)', '',
              '| round | extension | held-out gain | p (Wilcoxon) | accepted | values |',
              '|---|---|---|---|---|---|']
    for cand in result.candidates:
        values = ', '.join(f'{k} = {_num(v)}' for k, v in cand.values.items())
        lines.append(f'| {cand.round_no} | {cand.name} | {cand.relative_gain:+.1%} | '
                     f'{cand.p_value:.2g} | {"yes" if cand.accepted else "no"} | {values} |')
    lines += ['', '## Residual correlations (strongest first)', '',
              '| residual | signal | r |', '|---|---|---|']
    lines += [f'| {c} | {s} | {r:+.3f} |' for c, s, r in result.trace.top(12)]
    lines += ['']
    lines += figure_lines(images, [('residuals', 'Residual against the explaining signal'),
                                   ('errors', 'Error distributions')], level='##')
    lines += provenance_lines(result.provenance)
    return '\n'.join(lines)


def write_diagnosis_report(result: DiagnosisResult, out_dir: str | Path,
                           force: bool = False) -> Path:
    """Write diagnosis.md and its PNGs into out_dir; return the path of diagnosis.md.

    An existing diagnosis.md needs ``force`` (OutputError otherwise); the folder is created.
    """
    folder, page = prepare_report(out_dir, 'diagnosis.md', force)
    images = {'residuals': residual_figure(result, folder / 'diagnosis_residuals.png').name,
              'errors': error_figure(result, folder / 'diagnosis_errors.png').name}
    return atomic_write_text(page, render_diagnosis_page(result, images), force=force)
