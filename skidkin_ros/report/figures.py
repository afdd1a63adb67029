"""The report's figures (matplotlib, Agg backend), each written to a PNG and its path returned."""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from skidkin_ros.atomic import atomic_write_bytes  # noqa: E402
from skidkin_ros.core.calibration.pipeline import CalibrationResult, HorizonStudy  # noqa: E402
from skidkin_ros.core.kinematics.models import get_model  # noqa: E402
from skidkin_ros.core.odometry.se2 import rollout_segments  # noqa: E402

__all__ = ['save_figure', 'error_distributions', 'rotation_per_metre', 'angular_error_map',
           'segment_paths', 'segment_paths_figure', 'horizon_figure']


def save_figure(fig, path: Path) -> Path:
    """Render to memory, then write atomically (never half a PNG); the caller checked force."""
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format='png', dpi=110)
    plt.close(fig)
    return atomic_write_bytes(path, buffer.getvalue(), force=True)


def error_distributions(result: CalibrationResult, path: Path) -> Path:
    """Violin and box plots of eps_t and eps_theta per model (the paper's overall errors)."""
    names = list(result.evaluation)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, attr, label in ((axes[0], 'eps_t', 'eps_t (m/m)'),
                            (axes[1], 'eps_theta_deg', 'eps_theta (deg/m)')):
        data = [getattr(result.evaluation[m], attr) for m in names]
        present = [i for i, d in enumerate(data) if d.size]
        if present:
            ax.violinplot([data[i] for i in present], positions=present, showextrema=False)
            ax.boxplot([data[i] for i in present], positions=present, widths=0.2,
                       showfliers=False)
        ax.set_xticks(range(len(names)), names, rotation=20)
        ax.set_ylabel(label)
        ax.set_yscale('log')
        ax.grid(alpha=0.3)
    fig.suptitle(f'Evaluation errors on {len(result.eval_segments)} segments '
                 f'(h_e = {result.options.h_e:g} m)')
    return save_figure(fig, path)


def rotation_per_metre(result: CalibrationResult, path: Path, bins: int = 12) -> Path:
    """Actual vs commanded (ideal differential drive) rotation per metre: median and quartiles."""
    seg = result.eval_segments
    ideal = get_model('ideal_dd')
    twist = ideal.twist(np.zeros(0), result.geometry, seg.omega_l, seg.omega_r)
    commanded = (twist[..., 2] * seg.dt_s).sum(axis=1)
    ok = seg.path_m >= result.options.min_eval_path_m
    cmd = np.degrees(commanded[ok]) / seg.path_m[ok]
    actual = np.degrees(seg.rotation_rad[ok]) / seg.path_m[ok]
    fig, ax = plt.subplots(figsize=(6, 4.5))
    if cmd.size:
        edges = np.quantile(cmd, np.linspace(0, 1, bins + 1))
        centres, med, q25, q75 = [], [], [], []
        for lo, hi in zip(edges[:-1], edges[1:]):
            sel = (cmd >= lo) & (cmd <= hi)
            if sel.sum() >= 3:
                centres.append(np.median(cmd[sel]))
                q = np.percentile(actual[sel], [25, 50, 75])
                q25.append(q[0])
                med.append(q[1])
                q75.append(q[2])
        ax.scatter(cmd, actual, s=5, alpha=0.3, color='grey', label='segments')
        ax.plot(centres, med, color='C0', label='median')
        ax.fill_between(centres, q25, q75, color='C0', alpha=0.3, label='quartiles')
        lim = np.nanmax(np.abs(cmd))
        ax.plot([-lim, lim], [-lim, lim], 'k--', lw=0.8, label='ideal')
    ax.set_xlabel('commanded rotation per metre, ideal DD on wheel speeds (deg/m)')
    ax.set_ylabel('actual rotation per metre (deg/m)')
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return save_figure(fig, path)


def angular_error_map(result: CalibrationResult, path: Path, model: str | None = None) -> Path:
    """Angular error per metre against mean left/right wheel speeds (the paper's heat map)."""
    model = model or result.best
    ev = result.evaluation[model]
    left, right = result.eval_segments.mean_wheel_speeds()
    fig, ax = plt.subplots(figsize=(6, 5))
    sc = ax.scatter(left[ev.scored], right[ev.scored], c=ev.eps_theta_deg, s=14, cmap='viridis')
    fig.colorbar(sc, ax=ax, label='eps_theta (deg/m)')
    ax.set_xlabel('mean left wheel speed (rad/s)')
    ax.set_ylabel('mean right wheel speed (rad/s)')
    ax.set_title(f'Angular error of {model}')
    ax.set_aspect('equal', adjustable='datalim')
    ax.grid(alpha=0.3)
    return save_figure(fig, path)


def segment_paths(result: CalibrationResult, path: Path, count: int = 4) -> Path:
    """Draw a few evaluation segments: each model's predicted path beside the true path.

    Every model starts at the segment's true start pose; the panels share one scale (equal
    axes, the same span), so a model that turns too much looks it in every panel.
    """
    return save_figure(segment_paths_figure(result, count), path)


def segment_paths_figure(result: CalibrationResult, count: int = 4):
    """Return the matplotlib figure of :func:`segment_paths` (one panel per segment)."""
    seg = result.eval_segments
    pick = np.unique(np.linspace(0, len(seg) - 1, min(count, len(seg))).round().astype(int))
    sub = seg.subset(pick)
    fig, axes = plt.subplots(1, len(pick), figsize=(3.2 * len(pick), 3.6), squeeze=False)
    extents = [[sub.start[i, :2], sub.end[i, :2]] for i in range(len(pick))]
    for i, ax in enumerate(axes[0]):
        track = _truth_path(result, sub, i)
        if track is not None:
            ax.plot(track[:, 0], track[:, 1], color='k', lw=2.2, alpha=0.6,
                    label='ground truth')
            extents[i].append(track)
    for name, fit in result.fits.items():
        model = get_model(name)
        k = model.vector(fit.values, result.geometry)
        poses = rollout_segments(model.twist(k, result.geometry, sub.omega_l, sub.omega_r),
                                 sub.dt_s, sub.start)
        for i, ax in enumerate(axes[0]):
            steps = int(sub.step_counts[i]) + 1
            ax.plot(poses[i, :steps, 0], poses[i, :steps, 1], label=name, lw=1)
            extents[i].append(poses[i, :steps, :2])
    span = max(float(np.ptp(np.vstack(e), axis=0).max()) for e in extents) * 0.55 + 0.05
    for i, ax in enumerate(axes[0]):
        ax.plot(*sub.start[i, :2], 'ko', ms=4)
        ax.plot(*sub.end[i, :2], 'k*', ms=9)
        centre = np.vstack(extents[i]).min(axis=0) / 2 + np.vstack(extents[i]).max(axis=0) / 2
        ax.set_xlim(centre[0] - span, centre[0] + span)
        ax.set_ylim(centre[1] - span, centre[1] + span)
        ax.set_aspect('equal', adjustable='box')
        ax.set_xlabel('x (m)', fontsize=8)
        ax.set_title(f'segment {int(pick[i])}', fontsize=9)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel('y (m)', fontsize=8)
    axes[0][0].legend(fontsize=6)
    fig.suptitle('Held-out segments from their true start pose: each model against the ground '
                 'truth (dot: start, star: true end)', fontsize=9)
    return fig


def _truth_path(result: CalibrationResult, sub, i: int) -> np.ndarray | None:
    """Return the (M, 2) ground-truth positions of segment ``i`` of ``sub``, or None."""
    drive = int(sub.drive[i])
    if drive >= len(result.eval_truth) or result.eval_truth[drive] is None:
        return None
    truth = result.eval_truth[drive]
    inside = (truth.t_ns >= sub.t_a_ns[i]) & (truth.t_ns <= sub.t_b_ns[i])
    if inside.sum() < 2:
        return None
    return np.column_stack([truth.x[inside], truth.y[inside]])


def horizon_figure(study: HorizonStudy, path: Path) -> Path:
    """Median and IQR of eps_t against h_e, one curve per h_t, for each model."""
    models = list(study.median)
    fig, axes = plt.subplots(len(models), 2, figsize=(9, 3 * len(models)), squeeze=False)
    for row, model in enumerate(models):
        for i, h_t in enumerate(study.h_t):
            axes[row][0].plot(study.h_e, study.median[model][i], marker='o', label=f'h_t={h_t:g}')
            axes[row][1].plot(study.h_e, study.iqr[model][i], marker='o', label=f'h_t={h_t:g}')
        axes[row][0].set_ylabel(f'{model}\nmedian eps_t (m/m)')
        axes[row][1].set_ylabel('IQR eps_t (m/m)')
        for ax in axes[row]:
            ax.set_xlabel('h_e (m)')
            ax.grid(alpha=0.3)
        axes[row][0].legend(fontsize=7)
    return save_figure(fig, path)
