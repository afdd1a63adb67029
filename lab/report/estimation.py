"""Figures of the estimation study (matplotlib, Agg): errors and NEES against the chi2 band.

The study (:mod:`lab.studies.estimation`) returns its numbers; this module draws them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

from lab.studies.estimation import EstimationStudy, FilterRuns  # noqa: E402
import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

from skidkin_ros.core.estimation.nees import DriveNees, NeesSummary, SegmentNees  # noqa: E402
from skidkin_ros.report.figures import save_figure  # noqa: E402

__all__ = ['error_over_time', 'nees_over_time_figure', 'segment_nees_figure',
           'drive_nees_figure', 'write_estimation_figures']


def error_over_time(runs: FilterRuns, path: Path) -> Path:
    """Position and yaw error vs time (RMS over the runs) for odometry alone and the filter."""
    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for errors, covs, label, colour in ((runs.odom_errors, runs.odom_covs, 'odometry alone',
                                         'tab:red'),
                                        (runs.ekf_errors, runs.ekf_covs, 'EKF + fixes',
                                         'tab:blue')):
        position = np.sqrt(np.mean(errors[..., 0] ** 2 + errors[..., 1] ** 2, axis=0))
        position_sd = np.sqrt(np.mean(covs[..., 0, 0] + covs[..., 1, 1], axis=0))
        yaw = np.degrees(np.sqrt(np.mean(errors[..., 2] ** 2, axis=0)))
        yaw_sd = np.degrees(np.sqrt(np.mean(covs[..., 2, 2], axis=0)))
        axes[0].plot(runs.t_s, position, color=colour, label=f'{label}: RMS error')
        axes[0].plot(runs.t_s, position_sd, color=colour, ls='--', lw=0.9,
                     label=f'{label}: predicted 1 sigma')
        axes[1].plot(runs.t_s, yaw, color=colour, label=f'{label}: RMS error')
        axes[1].plot(runs.t_s, yaw_sd, color=colour, ls='--', lw=0.9)
    axes[0].set_ylabel('position error (m)')
    axes[0].set_yscale('log')
    axes[1].set_ylabel('yaw error (deg)')
    axes[1].set_yscale('log')
    axes[1].set_xlabel('time (s)')
    axes[0].legend(fontsize=8)
    axes[0].set_title(f'Errors over {runs.odom_errors.shape[0]} held-out drives')
    return save_figure(fig, path)


def nees_over_time_figure(runs: FilterRuns, path: Path) -> Path:
    """Run-averaged NEES vs time for both estimators with the chi2 95 % band for M runs."""
    ekf = runs.ekf_nees_over_time()
    odom = runs.odom_nees_over_time()
    fig, ax = plt.subplots(figsize=(9, 4))
    ax.plot(odom.t_s, odom.mean, color='tab:red', lw=0.8, label='odometry alone')
    ax.plot(ekf.t_s, ekf.mean, color='tab:blue', lw=0.8, label='EKF + fixes')
    ax.axhspan(ekf.band[0], ekf.band[1], color='tab:green', alpha=0.2,
               label=f'chi2 95 % band ({ekf.runs} runs, 3 dof)')
    ax.axhline(3.0, color='k', lw=0.6, ls=':')
    ax.set_yscale('log')
    ax.set_xlabel('time (s)')
    ax.set_ylabel('average NEES')
    ax.legend(fontsize=8)
    ax.set_title(f'EKF: {100 * ekf.share_inside:.0f} % of samples inside the band')
    return save_figure(fig, path)


def segment_nees_figure(odometry: SegmentNees, horizons: Mapping[float, NeesSummary],
                        path: Path) -> Path:
    """Odometry alone: NEES histogram vs chi2(3), and average NEES per window length."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    values = odometry.nees
    top = float(np.quantile(values, 0.99)) if values.size else 10.0
    bins = np.linspace(0.0, max(top, 12.0), 40)
    axes[0].hist(np.clip(values, 0, bins[-1]), bins=bins, density=True, alpha=0.6,
                 label=f'{values.size} windows of {odometry.horizon_m:g} m')
    grid = np.linspace(1e-3, bins[-1], 200)
    axes[0].plot(grid, stats.chi2.pdf(grid, 3), 'k', label='chi2, 3 dof')
    axes[0].set_xlabel('NEES')
    axes[0].set_ylabel('density')
    axes[0].legend(fontsize=8)
    lengths = sorted(horizons)
    means = [horizons[h].mean for h in lengths]
    low = [horizons[h].band[0] for h in lengths]
    high = [horizons[h].band[1] for h in lengths]
    axes[1].fill_between(lengths, low, high, color='tab:green', alpha=0.2,
                         label='chi2 95 % band')
    axes[1].plot(lengths, means, 'o-', color='tab:red', label='average NEES')
    axes[1].axvline(odometry.horizon_m, color='k', lw=0.6, ls=':',
                    label='calibration horizon h_e')
    axes[1].set_xscale('log')
    axes[1].set_xticks(lengths)
    axes[1].set_xticklabels([f'{h:g}' for h in lengths])
    axes[1].minorticks_off()
    axes[1].set_xlabel('window length (m)')
    axes[1].set_ylabel('average NEES (3 dof)')
    axes[1].legend(fontsize=8)
    fig.suptitle('Odometry alone on independent windows of held-out drives')
    return save_figure(fig, path)


def drive_nees_figure(whole: DriveNees, horizons: Mapping[float, NeesSummary],
                      path: Path) -> Path:
    """Average NEES against the distance from the start of whole drives, with its chi2 band.

    The windows' average NEES (independent windows of each length) is drawn beside it: windows
    show the noise at one horizon, whole drives add the parameter error.
    """
    summaries = whole.summaries()
    distances = sorted(summaries)
    fig, ax = plt.subplots(figsize=(9, 4.5))
    ax.scatter(np.maximum(whole.checkpoint_distance_m, 0.5), whole.checkpoint_nees, s=6,
               color='0.6', label=f'every {whole.checkpoint_s:g} s of every drive')
    ax.fill_between(distances, [summaries[d].band[0] for d in distances],
                    [summaries[d].band[1] for d in distances], color='tab:green', alpha=0.2,
                    label=f'chi2 95 % band of the average ({whole.nees.shape[0]} drives)')
    ax.plot(distances, [summaries[d].mean for d in distances], 'o-', color='tab:red',
            label='whole drives: average NEES at that distance from the start')
    lengths = sorted(horizons)
    ax.plot(lengths, [horizons[h].mean for h in lengths], 's--', color='tab:blue',
            label='independent windows of that length')
    ax.axhline(3.0, color='k', lw=0.6, ls=':')
    ax.set_xscale('log')
    ax.set_yscale('log')
    ax.set_xlabel('distance from the start (m)')
    ax.set_ylabel('NEES (3 dof)')
    ax.legend(fontsize=8)
    ax.set_title('Odometry alone: is the published covariance honest from 1 m to a whole drive?')
    return save_figure(fig, path)


def write_estimation_figures(out_dir: Path, study: EstimationStudy) -> dict[str, Path]:
    """Write the study's figures into ``out_dir`` (created) and return name -> path."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    runs = study.runs
    figures = {'error_over_time': error_over_time(runs, out_dir / 'estimation_error.png'),
               'nees_over_time': nees_over_time_figure(runs, out_dir / 'estimation_nees.png'),
               'segment_nees': segment_nees_figure(study.odometry, study.horizons,
                                                   out_dir / 'odometry_nees.png')}
    if study.whole is not None:
        figures['drive_nees'] = drive_nees_figure(study.whole, study.horizons,
                                                  out_dir / 'drive_nees.png')
    return figures
