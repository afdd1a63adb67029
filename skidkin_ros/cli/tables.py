"""Plain-text tables printed by the ``skidkin`` commands."""

from __future__ import annotations

import math
from typing import Mapping

from skidkin_ros.core.calibration.evaluation import ModelEvaluation, WindowEnd
from skidkin_ros.core.calibration.fitting import FitResult
from skidkin_ros.core.calibration.gyro_windows import ModeScore
from skidkin_ros.core.calibration.noise_fit import NoiseFit
from skidkin_ros.core.calibration.selection import Likelihood
from skidkin_ros.core.estimation.nees import summarize_nees
from skidkin_ros.core.odometry.config import OdometryConfig

__all__ = ['error_table', 'imu_table', 'parameter_lines']


def _f(value: float, digits: int = 3) -> str:
    return 'nan' if not math.isfinite(value) else f'{value:.{digits}g}'


def error_table(evaluation: Mapping[str, ModelEvaluation],
                fits: Mapping[str, FitResult] | None = None,
                noise: Mapping[str, NoiseFit] | None = None, best: str | None = None,
                window_end: Mapping[str, WindowEnd] | None = None,
                likelihood: Mapping[str, Likelihood] | None = None) -> str:
    """Return eps_t (m/m) and eps_theta (deg/m): median [q25, q75] p90 per model.

    Optional columns: the median heading error at held-out window ends (rad), the share of
    held-out errors inside the predicted 95 % region and the coverage factor, the held-out NLL
    per segment with its paired difference to the lowest (and 2 clustered standard errors).
    """
    header = (f'{"model":<15} {"eps_t m/m  median [q25, q75]   p90":<38}'
              f'{"eps_theta deg/m  median [q25, q75]   p90":<44}{"segs":>5}')
    if window_end:
        header += '  end yaw'
    if noise is not None:
        header += '  in 95%  cov x'
    if likelihood:
        header += '  NLL/seg  dNLL (2 SE)   '
    if fits is not None:
        header += '  fit'
    lines = [header, '-' * (len(header) + 10)]
    for name, ev in evaluation.items():
        t, th = ev.stats_t, ev.stats_theta
        row = (f'{name:<15} '
               + f'{_f(t.median)} [{_f(t.q25)}, {_f(t.q75)}]  {_f(t.p90)}'.ljust(38)
               + f'{_f(th.median)} [{_f(th.q25)}, {_f(th.q75)}]  {_f(th.p90)}'.ljust(44)
               + f'{t.count:>5}')
        if window_end:
            end = window_end.get(name)
            row += f'  {_f(end.yaw_rad) if end else "-":>7}'
        if noise is not None:
            fitted = noise.get(name)
            row += ('      -       -' if fitted is None else
                    f'  {fitted.consistency.inside_95_3dof * 100:5.1f}%'
                    f'  {fitted.coverage_scale:5.2f}')
        if likelihood:
            row += _likelihood_cells(likelihood.get(name))
        if fits is not None and name in fits:
            row += '  ok' if fits[name].valid else '  INVALID'
        if name == best:
            row += '  <- best'
        lines.append(row)
    return '\n'.join(lines)


def _likelihood_cells(entry: Likelihood | None) -> str:
    if entry is None:
        return '        -  -'.ljust(33)
    if not math.isfinite(entry.mean_nll):
        return '      inf  -'.ljust(33)
    if entry.delta == 0.0:
        delta = 'lowest'
    else:
        delta = f'{entry.delta:+.3f} ({2 * entry.standard_error:.3f})'
    return f'  {entry.mean_nll:+7.3f}  {delta}'.ljust(33)


def parameter_lines(fits: Mapping[str, FitResult]) -> list[str]:
    lines = []
    for name, fit in fits.items():
        if not fit.values:
            continue
        parts = []
        for param, value in fit.values.items():
            err = fit.std_errors.get(param, math.nan) if fit.std_errors else math.nan
            parts.append(f'{param}={value:.4g}' + (f' ±{err:.2g}' if math.isfinite(err) else '')
                         + (' (on its constraint: a valid constrained minimum)'
                            if param in fit.at_constraint else ''))
        lines.append(f'  {name:<15} ' + ', '.join(parts))
    return lines


def imu_table(scores: Mapping[str, ModeScore], config: OdometryConfig) -> str:
    """Return the errors per model and imu mode, with the errors at each drive's end and NEES.

    NEES: the mean over the windows (segments run from the true pose with a zero covariance)
    against the 95 % band of that mean for 3 dof; '-' without a calibrated noise model.
    """
    imu = config.imu
    lines = [f'gyro: scale {imu.scale:.4f}, bias {imu.bias:+.5f} rad/s, time offset '
             f'{imu.time_offset * 1e3:+.0f} ms (imu.* of the parameters file)',
             f'{"model mode":<22} {"eps_t m/m median / p90":<24}'
             f'{"eps_theta deg/m median / p90":<30}{"end pos m med / p90":<21}'
             f'{"end yaw deg med / p90":<23}{"segs":>5}  {"NEES [95 % band] (windows)"}']
    lines.append('-' * len(lines[-1]))
    for name, score in scores.items():
        t, th = score.evaluation.stats_t, score.evaluation.stats_theta
        pos, yaw = score.end_position_m, score.end_yaw_deg
        nees = '-'
        if score.nees.size:
            summary = summarize_nees(score.nees, 3)
            nees = (f'{_f(summary.mean)} [{summary.band[0]:.2f}, {summary.band[1]:.2f}] '
                    f'({summary.count})')
        lines.append(f'{name:<22} ' + f'{_f(t.median)} / {_f(t.p90)}'.ljust(24)
                     + f'{_f(th.median)} / {_f(th.p90)}'.ljust(30)
                     + f'{_f(pos.median)} / {_f(pos.p90)}'.ljust(21)
                     + f'{_f(yaw.median)} / {_f(yaw.p90)}'.ljust(23) + f'{t.count:>5}  {nees}')
    return '\n'.join(lines)
