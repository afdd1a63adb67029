"""Online calibration on the real Husky windows, beside what users run instead.

``data/husky/drive_husky_windows.csv`` (Clearpath Husky A200, DRIVE project) has 603 windows of
2 s at 20 Hz: wheel speeds, a gyro and lidar-ICP poses (about 10 Hz, held onto the 20 Hz grid).
The ICP poses are the kind of reference the node takes on ``reference/odom``. The recipe:

1. **The windows in time order, one stream.** Each window is placed on one clock, 4 s after the
   last one started (a 2 s gap between windows: longer than ``online.max_gap``, so each window
   is a new chain of the reference, as after a loss). One odometer (the node's, built by
   :func:`skidkin_ros.core.online.online_odometer`) runs them all through
   :meth:`Odometer.predict`, each window from its first ICP pose; what it learned is carried
   from window to window, as one node would carry it.
2. **The reference**: the window's ICP poses with the held repeats dropped
   (:func:`skidkin_ros.core.drive.fresh_pose_mask`), at the stamps of the rows they first
   appear on (about 10 Hz), handed over in stamp order as the node receives them: nothing of a
   window's future reaches its past.
3. **Split by ``calib_step``** as ``skidkin calibrate --split-by calib_step`` splits it: even
   steps train the offline files, odd steps are scored. The online odometry learns from every
   window's reference as it comes (it is causal: a window's odometry uses only the reference
   poses already passed), and is scored on the odd windows, like the others.
4. **The files compared**: ideal differential drive with the published geometry (what
   diff_drive_controller computes), the same with Clearpath's ``wheel_separation_multiplier``
   1.875, the calibrator's plain least-squares fit (``--weighting fixed``) and its calibrated
   fit (iterated weighting, noise), each run fixed, and online learning started from the ideal
   file and from the calibrated one; with the gyro fused (``imu.mode fuse``, the calibrated
   ``imu.*``) for the calibrated file, fixed and online.
5. **Scores by the project's evaluation code**: the evaluation segments of ``skidkin evaluate``
   (:func:`cut_segments`, h_e = 2 m: a window shorter than 2 m is one segment),
   :func:`odometry_segment_errors` and :func:`relative_errors` (ε_t m/m, ε_θ deg/m), and the
   NEES of the published pose at each scored window's end (:func:`window_nees`).

``online.horizon`` / ``online.horizon_rad`` (a learning segment closes after this reference
path or turning) default to the calibrator's 2 m / 1 rad; a window here drives 0.89 m and turns
0.82 rad in the median, so at the defaults few windows close a segment at all (a segment never
spans a reference gap). :data:`HORIZON` is half the median window.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from scipy import stats

from skidkin_ros.adapters.sources import load_source, SourceOptions
from skidkin_ros.core.calibration.evaluation import relative_errors
from skidkin_ros.core.calibration.gyro_windows import odometry_segment_errors, window_nees
from skidkin_ros.core.calibration.pipeline import calibrate_interval
from skidkin_ros.core.calibration.results import CalibrationOptions, result_to_parameters
from skidkin_ros.core.calibration.segments import (cut_segments, segment_frame_error,
                                                   SegmentOptions, SegmentSet)
from skidkin_ros.core.drive import Drive, fresh_pose_mask, ImuSamples, PoseTrack, WheelSamples
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.odometer import Prediction
from skidkin_ros.core.online import online_odometer

__all__ = ['CSV', 'GEOMETRY', 'HORIZON', 'MULTIPLIER', 'Window', 'Run', 'load_windows',
           'offline_file', 'ideal_file', 'with_values', 'reference_of', 'run_stream', 'score',
           'learned_at', 'run_study', 'tables']

CSV = Path(__file__).resolve().parents[2] / 'data' / 'husky' / 'drive_husky_windows.csv'
# Clearpath's published Husky A200 geometry and its odometry's separation multiplier.
GEOMETRY = Geometry(wheel_radius=0.1651, track_width=0.555)
MULTIPLIER = 1.875
MODEL = 'edd_symmetric'   # what `skidkin calibrate` writes for this data (docs/results.md)
# online.horizon (m) and online.horizon_rad (rad): half the median window (0.89 m, 0.82 rad).
HORIZON = (0.5, 0.5)
# Windows on one clock: each starts this long after the last one started (2 s gap).
PERIOD_NS = 4_000_000_000
START_NS = 1_000_000_000
H_E = 2.0
CHI2_95_3 = float(stats.chi2.ppf(0.95, 3))
# Scored windows over which "reaches the offline fit" is judged (the next ones, in time order).
RUN_WINDOWS = 40


@dataclass(frozen=True)
class Window:
    """One 2 s window on the stream's clock: its drive, time-order index and split."""

    index: int
    drive: Drive
    held_out: bool
    path_m: float


def _shift(drive: Drive, offset_ns: int) -> Drive:
    """Return the drive with every stamp moved by offset_ns (the stream's clock)."""
    w, truth, imu = drive.wheels, drive.truth, drive.imu
    return Drive(drive.name,
                 WheelSamples(w.t_ns + offset_ns, w.omega_l, w.omega_r),
                 PoseTrack(truth.t_ns + offset_ns, truth.x, truth.y, truth.yaw, truth.valid),
                 None if imu is None else ImuSamples(imu.t_ns + offset_ns, imu.yaw_rate),
                 drive.meta)


def load_windows(path: Path = CSV, limit: int | None = None) -> list[Window]:
    """Return the table's windows in time order (``segment``), each on the stream's clock."""
    drives = load_source(path, SourceOptions()).drives[:limit]
    out = []
    for index, drive in enumerate(drives):
        offset = START_NS + index * PERIOD_NS - int(drive.wheels.t_ns[0])
        shifted = _shift(drive, offset)
        out.append(Window(index, shifted, int(drive.meta['calib_step']) % 2 == 1,
                          float(shifted.truth.path_length()[-1])))
    return out


def reference_of(window: Window) -> PoseTrack:
    """Return the window's ICP poses without the held repeats (about 10 Hz)."""
    truth = window.drive.truth
    keep = fresh_pose_mask(truth.x, truth.y, truth.yaw)
    return PoseTrack(truth.t_ns[keep], truth.x[keep], truth.y[keep], truth.yaw[keep])


def offline_file(windows: Sequence[Window], weighting: str = 'iterated') -> OdometryConfig:
    """Return ``skidkin calibrate --split-by calib_step``'s file (``--weighting`` as given).

    Trained on the even windows, its noise and sample interval chosen on the odd ones, as the
    command does (models ideal_dd and edd_symmetric: the one it writes for this data).
    """
    train = [w.drive for w in windows if not w.held_out]
    evaluate = [w.drive for w in windows if w.held_out]
    options = CalibrationOptions(models=('ideal_dd', MODEL), holdout_every=2,
                                 holdout_key='calib_step', weighting=weighting)
    result = calibrate_interval(train, evaluate, GEOMETRY, options)
    flat = result_to_parameters(result, {'robot': 'husky_a200'})
    flat['model'] = MODEL
    return OdometryConfig.from_flat(flat)


def ideal_file(calibrated: OdometryConfig, multiplier: float = 1.0) -> OdometryConfig:
    """Return ideal differential drive (b = track_width x multiplier), uncalibrated noise.

    diff_drive_controller's odometry with ``wheel_separation_multiplier``: edd_symmetric with
    alpha 1 and b_hat the multiplied separation; the sample interval of the calibrated file.
    """
    return OdometryConfig.from_flat({
        'robot': 'husky_a200', 'wheel_radius': GEOMETRY.wheel_radius,
        'track_width': GEOMETRY.track_width, 'model': MODEL, 'interval': calibrated['interval'],
        f'models.{MODEL}.alpha': 1.0,
        f'models.{MODEL}.b_hat': GEOMETRY.track_width * multiplier})


def with_values(config: OdometryConfig, values: Mapping[str, object]) -> OdometryConfig:
    """Return the configuration with ``values`` set on top (validated again)."""
    return OdometryConfig.from_flat({**config.values, **values})


@dataclass
class Run:
    """One odometry over the stream: per window its prediction and the parameters after it."""

    name: str
    predictions: list[Prediction]
    values: list[dict[str, float]] = field(default_factory=list)
    counters: dict[str, int] = field(default_factory=dict)
    summary: dict[str, object] = field(default_factory=dict)


def run_stream(name: str, config: OdometryConfig, windows: Sequence[Window],
               reference_until: int | None = None, training_only: bool = False) -> Run:
    """Run one odometer over the windows in order; the reference up to window reference_until.

    ``reference_until`` (a window index): the windows from there on get no reference (a
    dropout to the end); None: every window has its reference (when online.enabled).
    ``training_only``: the held-out windows get no reference (what is scored there was learned
    on other commands only).
    """
    odometer = online_odometer(config)
    learner = odometer.learner
    run = Run(name, [])
    for window in windows:
        drive = window.drive
        reference = None
        if learner is not None and (reference_until is None or window.index < reference_until
                                    ) and not (training_only and window.held_out):
            reference = reference_of(window)
        run.predictions.append(odometer.predict(drive.wheels, drive.truth.poses[0], drive.imu,
                                                reference=reference))
        if learner is not None:
            run.values.append(dict(learner.values))
    run.counters = {k: int(v) for k, v in odometer.counters.items()
                    if k.startswith(('reference_', 'online_'))}
    if learner is not None:
        run.summary = learner.summary()
    return run


@dataclass(frozen=True)
class Score:
    """ε_t, ε_θ per scored segment and the window-end NEES of one run on some windows."""

    eps_t: np.ndarray          # m/m, per segment
    eps_theta: np.ndarray      # deg/m, per segment
    segment_window: np.ndarray  # the window index (time order) of each scored segment
    nees: np.ndarray           # per window (NaN where the covariance is the fallback's)


def score(run: Run, windows: Sequence[Window], pick: Sequence[int], interval: str,
          calibrated_noise: bool) -> Score:
    """Score a run on the windows ``pick`` (indices into ``windows``) by the project's code."""
    drives = [windows[i].drive for i in pick]
    segments: SegmentSet = cut_segments(drives, SegmentOptions(horizon_m=H_E,
                                                               interval=interval))
    predictions = [run.predictions[i] for i in pick]
    errors = odometry_segment_errors(predictions, segments)
    eps_t, eps_theta = relative_errors(errors, segments.path_m)
    scored = segments.path_m >= 0.1
    owner = np.asarray(pick)[segments.drive[scored].astype(int)]
    nees = np.full(len(pick), math.nan)
    if calibrated_noise:
        errs, covs = [], []
        for drive, pred in zip(drives, predictions):
            start = drive.truth.poses[0]
            end = drive.truth.interpolate(pred.t_ns[-1])
            errs.append(segment_frame_error(start[None], end[None], pred.poses[-1][None])[0])
            c, s = math.cos(start[2]), math.sin(start[2])
            rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
            cov = pred.pose_covariances[-1][np.ix_([0, 1, 5], [0, 1, 5])]
            covs.append(rot @ cov @ rot.T)
        nees = window_nees(np.array(errs), np.array(covs))
    return Score(eps_t, eps_theta, owner, nees)


def per_window(s: Score, pick: Sequence[int]) -> np.ndarray:
    """Return the mean ε_t of each picked window's scored segments (NaN: none scored)."""
    out = np.full(len(pick), math.nan)
    where = {w: k for k, w in enumerate(pick)}
    for w in np.unique(s.segment_window):
        out[where[int(w)]] = float(s.eps_t[s.segment_window == w].mean())
    return out


def learned_at(online: np.ndarray, offline: np.ndarray, within: float = 1.05,
               run: int = RUN_WINDOWS) -> int | None:
    """Return where online's ε_t stays within ``within`` x the offline file's (None: never).

    The first position from which the mean over the next ``run`` windows is within, and is
    so from every later position too.
    """
    ok = np.isfinite(online) & np.isfinite(offline)
    a, b = online[ok], offline[ok]
    index = np.nonzero(ok)[0]
    good = [a[i:i + run].mean() <= within * b[i:i + run].mean()
            for i in range(len(a) - run + 1)]
    for i in range(len(good)):
        if all(good[i:]):
            return int(index[i])
    return None


@dataclass
class Study:
    """Everything the tables print."""

    windows: list[Window]
    files: dict[str, OdometryConfig]
    runs: dict[str, Run]
    scores: dict[str, Score]
    late_scores: dict[str, Score]
    learned: dict[str, dict[str, object]]
    dropout_from: int
    horizon: tuple[float, float]


FIXED = ('ideal', f'ideal x{MULTIPLIER}', 'plain least squares', 'calibrated')


def run_study(limit: int | None = None, horizon: tuple[float, float] = HORIZON,
              settings: Mapping[str, float] | None = None, gyro: bool = True,
              default_horizon: bool = True) -> Study:
    """Run every odometry of the comparison on the windows (the first ``limit``)."""
    windows = load_windows(limit=limit)
    calibrated = offline_file(windows)
    files = {'ideal': ideal_file(calibrated), f'ideal x{MULTIPLIER}':
             ideal_file(calibrated, MULTIPLIER),
             'plain least squares': offline_file(windows, 'fixed'), 'calibrated': calibrated}
    online = {'online.enabled': True, 'online.horizon': horizon[0],
              'online.horizon_rad': horizon[1], **(settings or {})}
    configs = dict(files)
    configs['online from ideal'] = with_values(files['ideal'], online)
    configs[f'online from ideal x{MULTIPLIER}'] = with_values(files[f'ideal x{MULTIPLIER}'],
                                                              online)
    configs['online from calibrated'] = with_values(calibrated, online)
    if default_horizon:
        configs['online from ideal, default horizon'] = with_values(
            files['ideal'], {**online, 'online.horizon': 2.0, 'online.horizon_rad': 1.0})
    if gyro:
        fuse = {'imu.mode': 'fuse'}
        configs['calibrated, gyro fused'] = with_values(calibrated, fuse)
        configs['online from ideal, gyro fused'] = with_values(
            files['ideal'], {**online, **_imu(calibrated), **fuse})
        configs['online from calibrated, gyro fused'] = with_values(calibrated,
                                                                    {**online, **fuse})
    runs = {name: run_stream(name, config, windows) for name, config in configs.items()}
    dropout_from = len(windows) // 2
    for start in ('ideal', 'calibrated'):
        name = f'online from {start}, reference on training windows only'
        runs[name] = run_stream(name, configs[f'online from {start}'], windows,
                                training_only=True)
    for start in ('ideal', 'calibrated'):
        name = f'online from {start}, no reference after half'
        runs[name] = run_stream(name, configs[f'online from {start}'], windows, dropout_from)
    interval = calibrated['interval']
    held = [w.index for w in windows if w.held_out]
    late = [i for i in held if i >= dropout_from]
    scores, late_scores = {}, {}
    for name, run in runs.items():
        noise = _config_of(name, configs).active_noise is not None
        scores[name] = score(run, windows, held, interval, noise)
        late_scores[name] = score(run, windows, late, interval, noise)
    learned = {}
    target = calibrated.model_values[MODEL]
    for name, run in runs.items():
        if not run.values or 'no reference' in name:
            continue
        online_w = per_window(scores[name], held)
        offline_w = per_window(scores['calibrated'], held)
        at = learned_at(online_w, offline_w)
        alpha = np.array([v['alpha'] for v in run.values])
        per_alpha = np.array([v['b_hat'] / v['alpha'] for v in run.values])
        learned[name] = {
            'windows': None if at is None else held[at],
            'metres': (None if at is None else
                       float(sum(w.path_m for w in windows[:held[at]]))),
            'alpha': np.percentile(alpha, [5, 50, 95]),
            'per_alpha': np.percentile(per_alpha, [5, 50, 95]),
            'file_per_alpha': target['b_hat'] / target['alpha']}
    return Study(windows, files, runs, scores, late_scores, learned, dropout_from, horizon)


def _imu(calibrated: OdometryConfig) -> dict[str, object]:
    """Return the calibrated file's gyro (imu.*) values: the ideal file has none of its own."""
    return {k: v for k, v in calibrated.values.items() if k.startswith('imu.')}


def _config_of(name: str, configs: Mapping[str, OdometryConfig]) -> OdometryConfig:
    return configs[name.split(', no reference')[0].split(', reference on')[0]]


def _fmt(value: float, digits: int = 3) -> str:
    return '–' if value is None or not np.isfinite(value) else f'{value:.{digits}g}'


def tables(study: Study) -> str:
    """Return the study's table (markdown) and the learning counts, as text."""
    calibrated = study.files['calibrated'].model_values[MODEL]
    lines = [f'{len(study.windows)} windows, {sum(w.path_m for w in study.windows):.0f} m; '
             f'scored: {sum(w.held_out for w in study.windows)} odd-calib_step windows; '
             f'online.horizon {study.horizon[0]:g} m, horizon_rad {study.horizon[1]:g} rad; '
             f'calibrated file: alpha {calibrated["alpha"]:.4f}, b_hat '
             f'{calibrated["b_hat"]:.4f} m, b_hat / alpha '
             f'{calibrated["b_hat"] / calibrated["alpha"]:.3f} m '
             f'(interval {study.files["calibrated"]["interval"]})',
             '',
             '| odometry | eps_t m/m median / mean / p90 | eps_th deg/m median / mean / p90 | '
             'window-end NEES mean (95 % inside) | last half: eps_t / eps_th median | '
             'reaches the calibrated file after windows (m) | alpha over the stream, 5 / 50 / '
             '95 % | b_hat / alpha (m), 5 / 50 / 95 % |',
             '|' + '---|' * 8]
    for name, s in study.scores.items():
        late = study.late_scores[name]
        nees = s.nees[np.isfinite(s.nees)]
        nees_txt = (f'{nees.mean():.2f} ({100 * (nees <= CHI2_95_3).mean():.0f} %)'
                    if nees.size else '– (fallback diagonals)')
        learn = study.learned.get(name)
        reach = params = final = '–'
        if learn is not None:
            reach = ('never' if learn['windows'] is None else
                     f'{learn["windows"]} ({learn["metres"]:.0f} m)')
            params = ' / '.join(f'{v:.3f}' for v in learn['alpha'])
            final = ' / '.join(f'{v:.3f}' for v in learn['per_alpha'])
        t = np.percentile(s.eps_t, [50, 90])
        th = np.percentile(s.eps_theta, [50, 90])
        lines.append(
            f'| {name} | {t[0]:.3f} / {s.eps_t.mean():.3f} / {t[1]:.3f} | {th[0]:.2f} / '
            f'{s.eps_theta.mean():.2f} / {th[1]:.1f} | {nees_txt} | '
            f'{np.median(late.eps_t):.3f} / {np.median(late.eps_theta):.2f} | {reach} | '
            f'{params} | {final} |')
    lines.append('')
    lines.append('learning counts (reference poses by outcome, learning events):')
    for name, run in study.runs.items():
        if run.counters:
            counts = ', '.join(f'{k} {v}' for k, v in sorted(run.counters.items()) if v)
            lines.append(f'  {name}: {counts}')
            lines.append(f'    grounds {run.summary.get("grounds")}, state at the end '
                         f'{run.summary.get("state")}, noise_scale '
                         f'{_fmt(run.summary.get("noise_scale"))}, reference sigma xy / yaw '
                         f'{_fmt(run.summary.get("reference_sigma_xy"))} / '
                         f'{_fmt(run.summary.get("reference_sigma_yaw"))}')
    return '\n'.join(lines)
