"""The calibration report page: report.md with tables and the figures beside it."""

from __future__ import annotations

import json
import math
from pathlib import Path

from skidkin_ros.atomic import atomic_write_text, check_writable
from skidkin_ros.core.calibration.pipeline import CalibrationResult, HorizonStudy
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.odometry.noise import NOISE_SPECS
from skidkin_ros.errors import OutputError
from skidkin_ros.report import figures

__all__ = ['write_report', 'render_page', 'prepare_report', 'figure_lines', 'provenance_lines']


def _num(value: float, digits: int = 4) -> str:
    return '–' if value is None or not math.isfinite(value) else f'{value:.{digits}g}'


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    lines = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
    lines += ['| ' + ' | '.join(row) + ' |' for row in rows]
    return lines


def figure_lines(images: dict[str, str], titles: list[tuple[str, str]], level: str = '###'
                 ) -> list[str]:
    """Return a Markdown heading and image for each (key, title) whose figure was made."""
    lines: list[str] = []
    for key, title in titles:
        if key in images:
            lines += [f'{level} {title}', '', f'![{title}]({images[key]})', '']
    return lines


def provenance_lines(provenance: object) -> list[str]:
    """Return the report's closing provenance section (JSON in a code block)."""
    return ['## Provenance', '', '```', json.dumps(provenance, indent=1, default=str), '```', '']


def _rule_text(rule: str) -> str:
    if rule == 'likelihood':
        return ('lowest held-out negative log-likelihood per segment under the calibrated noise; '
                'a model with fewer parameters is taken within 2 paired standard errors, '
                'clustered by drive or hold-out group')
    return ('lowest sum of medians of eps_t and eps_theta, each relative to the best valid '
            'model; within 2 % the model with fewer parameters wins')


def render_page(result: CalibrationResult, images: dict[str, str]) -> str:
    """Return the Markdown text of the report (images: figure key -> file name)."""
    lines = ['# skidkin_ros calibration report', '',
             f'Geometry: wheel radius r = {result.geometry.wheel_radius:g} m, track width '
             f'b = {result.geometry.track_width:g} m. Training horizon h_t = '
             f'{result.options.h_t:g} m, evaluation horizon h_e = {result.options.h_e:g} m; '
             f'evaluation data: {result.holdout}.', '',
             f'**Best model: `{result.best}`** ({_rule_text(result.selection_rule)}). Fit: '
             f'{result.options.weighting} weighting.', '',
             '## Evaluation errors (per metre of ground-truth path)', '']
    rows = []
    for name, ev in result.evaluation.items():
        st, sth = ev.stats_t, ev.stats_theta
        fit = result.fits[name]
        end = result.window_end.get(name)
        like = result.likelihood.get(name)
        rows.append([f'`{name}`', 'yes' if fit.valid else '**no**',
                     f'{_num(st.median)} [{_num(st.q25)}, {_num(st.q75)}]', _num(st.p90),
                     f'{_num(sth.median)} [{_num(sth.q25)}, {_num(sth.q75)}]', _num(sth.p90),
                     str(st.count), _num(end.yaw_rad if end else math.nan, 3),
                     _num(like.mean_nll if like else math.nan, 3),
                     _num(like.delta if like else math.nan, 3)
                     + (f' ({_num(2 * like.standard_error, 2)})' if like else ''),
                     _num(result.scores.get(name, math.nan), 3)])
    lines += _table(['model', 'valid', 'eps_t m/m median [q25, q75]', 'eps_t p90',
                     'eps_theta deg/m median [q25, q75]', 'eps_theta p90', 'segments',
                     'end yaw rad', 'NLL/segment', 'dNLL (2 SE)', 'paper score'], rows)
    lines += ['', '## Fitted parameters (value ± standard error)', '']
    rows = []
    for name, fit in result.fits.items():
        model = get_model(name)
        for spec in model.params:
            flag = ''
            if spec.name in fit.on_bound:
                flag = 'on bound'
            if spec.name in fit.at_constraint:
                flag = 'on its constraint (valid)'
            if spec.name in fit.unobservable:
                flag = 'not observable'
            value = _num(fit.values[spec.name], 5)
            error = _num(fit.std_errors[spec.name], 2)
            rows.append([f'`{name}`', spec.name, f'{value} ± {error}',
                         spec.unit, spec.fit_range_text(), flag])
    lines += _table(['model', 'parameter', 'value', 'unit', 'bounds', 'note'], rows)
    if 'edd_symmetric' in result.fits:
        b_hat = result.fits['edd_symmetric'].values['b_hat']
        lines += ['', f'Virtual track width: b_hat / b = {b_hat / result.geometry.track_width:.3f}'
                  ' (what diff_drive_controller calls wheel_separation_multiplier).']
    lines += ['', '## Fit status', '']
    rows = [[f'`{n}`', str(f.converged), str(f.segments_used), str(f.segments_trimmed),
             str(f.starts), _num(f.cost), f'{f.seconds:.2f}'] for n, f in result.fits.items()]
    lines += _table(['model', 'converged', 'segments', 'trimmed', 'starts', 'cost',
                     'time s'], rows)
    lines += ['', '## Noise model (variance growth) and consistency', '',
              'Consistency: share of held-out segment errors inside the predicted 95 % region '
              '(chi2, 3 dof on x, y, yaw; 2 dof on position), two-fold; goal ~95 %. Coverage '
              'scale: the factor (>= 1) applied to the maximum-likelihood rates so that they '
              'cover 95 % of the errors they were fitted on (real skid has heavier tails than '
              'a Gaussian; 1 means no change).', '']
    rows = []
    for name, nf in result.noise.items():
        nd = nf.noise.as_dict()
        rows.append([f'`{name}`'] + [_num(nd[k], 3) for k in nd]
                    + [f'{nf.coverage_scale:.2f}',
                       f'{100 * nf.consistency.inside_95_3dof:.1f} %',
                       f'{100 * nf.consistency.inside_95_position_2dof:.1f} %'])
    lines += _table(['model'] + [spec.name for spec in NOISE_SPECS]
                    + ['coverage scale', 'inside 95 % (3 dof)', 'inside 95 % (2 dof)'], rows)
    lines += ['', '## Segments', '', '```', json.dumps(result.counts, indent=1), '```']
    if result.warnings:
        lines += ['', '## Warnings', ''] + [f'- {w}' for w in result.warnings]
    lines += ['', '## Figures', '']
    lines += figure_lines(images, [('errors', 'Error distributions per model'),
                                   ('rotation', 'Actual vs commanded rotation per metre'),
                                   ('angular', 'Angular error against wheel speeds'),
                                   ('paths', 'Predicted vs ground-truth paths of a few segments'),
                                   ('horizons', 'h_t x h_e study')])
    lines += provenance_lines(result.provenance)
    return '\n'.join(lines)


def prepare_report(out_dir: str | Path, page_name: str, force: bool) -> tuple[Path, Path]:
    """Create the report folder and check its page may be written; return (folder, page).

    An existing page needs ``force`` (OutputError otherwise), checked before any figure is made.
    """
    folder = Path(out_dir)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f'cannot create report folder {folder}: {err}') from err
    return folder, check_writable(folder / page_name, force)


def write_report(result: CalibrationResult, out_dir: str | Path, force: bool = False,
                 study: HorizonStudy | None = None) -> Path:
    """Write report.md and its PNGs into out_dir; return the path of report.md.

    An existing report.md needs ``force`` (OutputError otherwise); the folder is created.
    """
    folder, page = prepare_report(out_dir, 'report.md', force)
    images = {}
    makers = [('errors', 'errors.png', figures.error_distributions),
              ('rotation', 'rotation_per_metre.png', figures.rotation_per_metre),
              ('angular', 'angular_error_map.png', figures.angular_error_map),
              ('paths', 'segment_paths.png', figures.segment_paths)]
    for key, name, maker in makers:
        maker(result, folder / name)
        images[key] = name
    if study is not None:
        figures.horizon_figure(study, folder / 'horizons.png')
        images['horizons'] = 'horizons.png'
    return atomic_write_text(page, render_page(result, images), force=force)
