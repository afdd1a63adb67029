"""Gyro study: off, adapt and fuse on simulated drives that change ground.

Training: effect-free drives of the simulator's default robot (true model ``edd_asymmetric``),
exact ground truth; ``full_linear`` calibrated on them (:func:`calibrate`: fit on two drives,
noise rates on a third).
Test drives, each run by its own odometer (the node's, :meth:`Odometer.predict`) in every mode,
with the simulator's 100 Hz gyro (noise 0.005 rad/s per sample, no bias, no offset):

* ``effect-free``: the calibration ground throughout;
* ``ground change``: ``terrain_regime`` (mode time): from half the drive on, v_x and the yaw rate
  lose the fraction k (a low-friction ground), for good;
* ``low-friction patch``: ``terrain_regime`` (mode region): the same wherever x > 1 m, so the
  robot drives on and off it again and again.

The reference column ("true model"): the simulator's true model on effect-free drives; on the
new ground, ``full_linear`` calibrated the same way on drives wholly on that ground (what a
fixed model would need to know). "settled": segments wholly on the
new ground that start at least 5 m (ground-truth path) after the change. Recovery: path from
the change until the learned gain is within 0.25 k of its new value 1 - k. NEES: windows of 2 m
of path, each started from the true pose with a zero pose covariance while the gyro history and
the gain and bias carry on (as after ``~/set_pose``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Iterator, Sequence

from lab.studies.effects import SIM_INTERVAL
import numpy as np

from skidkin_ros.core.calibration.evaluation import ErrorStats, evaluate_model, relative_errors
from skidkin_ros.core.calibration.gyro_fit import (odometry_segment_errors, run_windows,
                                                   segment_windows, window_nees)
from skidkin_ros.core.calibration.pipeline import (calibrate, CalibrationOptions,
                                                   result_to_parameters)
from skidkin_ros.core.calibration.segments import cut_segments, SegmentOptions
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.estimation.nees import summarize_nees
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.odometer import Odometer, Prediction
from skidkin_ros.sim.effects import make_effect
from skidkin_ros.sim.simulate import SimConfig, simulate

__all__ = ['GEOMETRY', 'MODEL', 'CASES', 'ImuCase', 'run_case', 'run_study', 'TABLE_HEADER']

GEOMETRY = Geometry(0.1651, 0.555)
MODEL = 'full_linear'
STRENGTH = 0.3
BOUNDARY_X_M = 1.0
SETTLE_M = 5.0
MODES = ('off', 'adapt', 'fuse')
CASES = ('effect-free', 'ground change', 'low-friction patch')
TABLE_HEADER = (
    '| drives | segments | true model | off | adapt | fuse | adapt recovery m (median / max) '
    '| NEES 2 m off / adapt / fuse [95 % band] |',
    '|---|---|---|---|---|---|---|---|')


def _effect(case: str):
    if case == 'new ground':
        return make_effect('terrain_regime', STRENGTH, mode='time', switch_frac=0.0)
    if case == 'ground change':
        return make_effect('terrain_regime', STRENGTH, mode='time', switch_frac=0.5)
    if case == 'low-friction patch':
        return make_effect('terrain_regime', STRENGTH, mode='region', boundary_x_m=BOUNDARY_X_M)
    return None


def _drives(case: str, seeds: Sequence[int], duration_s: float) -> list[Drive]:
    effect = _effect(case)
    return [simulate(SimConfig(duration_s=duration_s, seed=seed,
                               effects=(effect,) if effect else ())).drive(f'{case}{seed}')
            for seed in seeds]


def calibrated_config(case: str = 'effect-free', seeds: Sequence[int] = (1, 2, 3),
                      duration_s: float = 120.0) -> OdometryConfig:
    """Return ``MODEL`` calibrated on drives of one case (with noise rates), as the file says."""
    drives = _drives(case, seeds, duration_s)
    # the simulator's speeds are the wheels' at each stamp: the trapezoid integrates them exactly
    result = calibrate(drives[:-1], drives[-1:], GEOMETRY,
                       CalibrationOptions(models=(MODEL,), interval=SIM_INTERVAL))
    flat = result_to_parameters(result)
    flat['model'] = MODEL
    # the simulator's gyro has a constant bias and no bias walk: declared as it is (the default
    # imu.q_bias, a real gyro's walk, grows the bias's heading variance over a drive without stops)
    flat['imu.q_bias'] = 0.0
    return OdometryConfig.from_flat(flat)


def _on_new_ground(case: str, drive: Drive, t_a: int, t_b: int) -> bool:
    if case == 'ground change':
        return bool(t_a >= _switch_ns(drive))
    if case == 'low-friction patch':
        truth = drive.truth
        inside = (truth.t_ns >= t_a) & (truth.t_ns <= t_b)
        return bool(np.all(truth.x[inside] > BOUNDARY_X_M))
    return False


def _switch_ns(drive: Drive) -> int:
    t = drive.wheels.t_ns
    return int(t[0] + 0.5 * (t[-1] - t[0]))


def _settled(case: str, drive: Drive, t_a: int, t_b: int) -> bool:
    if not _on_new_ground(case, drive, t_a, t_b):
        return False
    if case != 'ground change':
        return True
    truth = drive.truth
    path = truth.path_length()
    return bool(np.interp(t_a, truth.t_ns, path) - np.interp(_switch_ns(drive), truth.t_ns, path)
                >= SETTLE_M)


@dataclass(frozen=True)
class ImuCase:
    """One case of the study: median errors per group and mode, recovery, NEES."""

    case: str
    groups: dict[str, dict[str, tuple[ErrorStats, ErrorStats]]]   # group -> mode -> (t, theta)
    recovery_m: tuple[float, ...]
    nees: dict[str, tuple[float, tuple[float, float], int]]       # mode -> (mean, band, count)

    def rows(self) -> list[str]:
        """Return the Markdown rows of the table in docs/results.md (one per group)."""
        out = []
        for group, modes in self.groups.items():
            cells = []
            for mode in ('true',) + MODES:
                if mode not in modes:
                    cells.append('-')
                    continue
                t, th = modes[mode]
                cells.append(f'{t.median:.4f} / {th.median:.3g}')
            count = modes['off'][0].count
            recovery = ('-' if not self.recovery_m else
                        f'{np.median(self.recovery_m):.2f} / {max(self.recovery_m):.2f}')
            nees_cell = '-'
            if self.nees and group == 'all':
                band = self.nees['off'][1]
                nees_cell = (' / '.join(f'{self.nees[m][0]:.2f}' for m in MODES)
                             + f' [{band[0]:.2f}, {band[1]:.2f}]')
            out.append(f'| {self.case} | {group} ({count}) | ' + ' | '.join(cells)
                       + f' | {recovery if group == "all" else "-"} | {nees_cell} |')
        return out


def run_case(case: str, config: OdometryConfig, reference: OdometryConfig,
             seeds: Sequence[int] = (11, 12, 13), duration_s: float = 120.0) -> ImuCase:
    """Run one case (module docstring) and return its scores."""
    drives = _drives(case, seeds, duration_s)
    options = SegmentOptions(horizon_m=2.0, short_drive='drop', interval=SIM_INTERVAL)
    segments = cut_segments(drives, options)
    predictions: dict[str, list[Prediction]] = {}
    nees_of: dict[str, list[np.ndarray]] = {}
    recovery: list[float] = []
    for mode in MODES:
        mode_config = replace(config, values={**config.values, 'imu.mode': mode})
        predictions[mode], nees_of[mode] = [], []
        for drive in drives:      # each drive by its own odometer, run in NEES windows
            own = cut_segments([drive], options)
            errors, covs, by_drive = run_windows(mode_config, [drive], own,
                                                 segment_windows([drive], own))
            pred = by_drive[0]
            predictions[mode].append(pred)
            nees_of[mode].append(window_nees(errors, covs))
            if mode == 'adapt' and case == 'ground change':
                recovery.append(_recovery_m(drive, pred))
    errors = {mode: odometry_segment_errors(predictions[mode], segments) for mode in MODES}
    settled = np.array([_settled(case, drives[int(segments.drive[k])], int(segments.t_a_ns[k]),
                                 int(segments.t_b_ns[k])) for k in range(len(segments))],
                       dtype=bool)
    ref_predictions = [Odometer.from_config(reference).predict(d.wheels, d.truth.poses[0])
                       for d in drives]
    ref_errors = odometry_segment_errors(ref_predictions, segments)
    groups: dict[str, dict[str, tuple[ErrorStats, ErrorStats]]] = {}
    selections = {'all': np.ones(len(segments), dtype=bool)}
    if case != 'effect-free':
        selections['on the new ground, settled' if case == 'ground change'
                   else 'wholly on the patch'] = settled
    for group, keep in selections.items():
        sub = segments.subset(keep)
        stats = {}
        for mode in MODES:
            eps_t, eps_theta = relative_errors(errors[mode][keep], sub.path_m)
            stats[mode] = (ErrorStats.of(eps_t), ErrorStats.of(eps_theta))
        if case == 'effect-free':
            evaluation = evaluate_model(SimConfig().true_model, SimConfig().true_params,
                                        GEOMETRY, sub)
            stats['true'] = (evaluation.stats_t, evaluation.stats_theta)
        elif group != 'all':
            eps_t, eps_theta = relative_errors(ref_errors[keep], sub.path_m)
            stats['true'] = (ErrorStats.of(eps_t), ErrorStats.of(eps_theta))
        groups[group] = stats
    nees_values = {}
    if case == 'effect-free':
        for mode in MODES:
            summary = summarize_nees(np.concatenate(nees_of[mode]), 3)
            nees_values[mode] = (summary.mean, summary.band, summary.count)
    return ImuCase(case, groups, tuple(recovery), nees_values)


def _recovery_m(drive: Drive, pred: Prediction) -> float:
    """Return the path (m) from the ground change until the gain is within 0.25 k of 1 - k."""
    t = drive.wheels.t_ns
    switch = _switch_ns(drive)
    after = t >= switch
    near = np.abs(pred.imu_gain - (1.0 - STRENGTH)) <= 0.25 * STRENGTH
    hits = np.nonzero(after & near)[0]
    if hits.size == 0:
        return float('inf')
    truth = drive.truth
    path = truth.path_length()
    return float(np.interp(t[hits[0]], truth.t_ns, path) - np.interp(switch, truth.t_ns, path))


def run_study(cases: Sequence[str] = CASES, seeds: Sequence[int] = (11, 12, 13),
              duration_s: float = 120.0) -> Iterator[ImuCase]:
    """Calibrate once, then yield each case's scores as it finishes."""
    config = calibrated_config()
    reference = calibrated_config('new ground')
    for case in cases:
        yield run_case(case, config, reference if case != 'effect-free' else config, seeds,
                       duration_s)
