"""The calibration's gyro step and plain-fit reference (steps 6 and 7 of the pipeline's recipe).

Step 6: with a gyro in the training data, its scale, bias and time offset, then adapt's filter
noise with the best model (:mod:`skidkin_ros.core.calibration.gyro_fit`). Step 7: the written
model fitted the plain way a user would, scored on the same held-out window ends. The recipe is in
:mod:`skidkin_ros.core.calibration.pipeline`.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Sequence

from skidkin_ros.core.calibration.evaluation import window_end_errors
from skidkin_ros.core.calibration.fitting import fit_model, FitOptions, FitResult
from skidkin_ros.core.calibration.gyro_fit import (fit_adapt_yaw_scale, fit_filter_noise,
                                                   fit_gyro, gyro_parameters, GyroFit)
from skidkin_ros.core.calibration.results import (CalibrationOptions, CalibrationResult,
                                                  result_to_parameters)
from skidkin_ros.core.calibration.segments import cut_segments
from skidkin_ros.core.drive import Drive
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.parallel import fork_map, usable_cpus
from skidkin_ros.errors import DataError, FitError, ParameterError

__all__ = ['plain_window_fit']


def plain_window_fit(name: str, geometry: Geometry, train: Sequence[Drive],
                     options: CalibrationOptions) -> FitResult:
    """Fit one model the plain way on the training windows (the pipeline's docstring, step 7).

    Every model gets the multi-start (the calibrator's own fit starts two-parameter models
    once): with spins in the windows the plain loss has local minima (a Warthog-like
    simulation: edd_symmetric from its default start ended at b_hat = 0.63 m, 1.49 rad of
    heading error at the window ends, against 1.70 m and 0.21 rad from the best of the
    starts), and the reference must be the best plain fit, not a weak one.
    """
    windows = cut_segments(train, replace(options.eval_segments(), horizon_s=options.window_s))
    return fit_model(name, geometry, windows, FitOptions(
        trim=False, seed=options.seed, n_starts=options.n_starts, multi_start_min_params=1))


def _add_plain_reference(result: CalibrationResult, train: Sequence[Drive],
                         evaluate: Sequence[Drive],
                         plain: FitResult | DataError | None = None) -> CalibrationResult:
    """Step 7: the written model's plain window-end fit, scored on the same window ends.

    ``plain``: that fit (or its DataError) when it was made already (:func:`_add_gyro`).
    """
    name = result.best
    if not get_model(name).params:
        return result
    options = result.options
    if plain is None:
        plain = _plain_fit(result, train)
    if isinstance(plain, DataError):
        return replace(result, warnings=result.warnings + (
            f'no plain window-end fit to compare with: {plain}',))
    windows = cut_segments(evaluate, replace(options.eval_segments(), horizon_s=options.window_s))
    end = window_end_errors(name, plain.values, result.geometry, windows)
    return replace(result, plain_window_end=end, plain_values=dict(plain.values))


def _plain_fit(result: CalibrationResult, train: Sequence[Drive]) -> FitResult | DataError:
    try:
        return plain_window_fit(result.best, result.geometry, train, result.options)
    except DataError as err:
        return err


def _add_gyro(result: CalibrationResult, train: Sequence[Drive], evaluate: Sequence[Drive],
              outcome: GyroFit | str | None = None, plain: bool = False) -> CalibrationResult:
    """Step 6 of the recipe: the gyro, when the training drives have one.

    ``plain``: step 7 too (:func:`_add_plain_reference`), its fit a parallel task beside the
    replay of the filter noise. That replay runs without the wheel noise: what it fits on (the
    filter's measurement and model rate, :func:`fit_filter_noise`) does not depend on the
    covariance, which is then not propagated.
    """
    warnings = list(result.warnings)
    gyro = None
    if any(drive.imu is not None for drive in train):
        outcome = outcome if outcome is not None else _fit_gyro_outcome(train)
        if isinstance(outcome, str):
            warnings.append(f'gyro not calibrated (imu.* not written): {outcome}')
        else:
            gyro = outcome
            if gyro.at_grid_edge:
                warnings.append(f'gyro time offset {gyro.time_offset:+.3f} s is at the edge of '
                                'the searched range: the gyro and wheel clocks may differ by '
                                'more; check the stamps')
    result = replace(result, warnings=tuple(warnings), gyro=gyro)
    eval_seg = result.eval_segments
    tasks = (('filter',) if gyro is not None else ()) + (
        ('plain',) if plain and get_model(result.best).params else ())
    done = dict(zip(tasks, fork_map(lambda task: _tail_task(task, result, train, evaluate),
                                    tasks, _jobs(result.options.jobs))))
    if gyro is not None:
        # adapt's filter noise: the written model and gyro on the drives the wheel noise is
        # fitted on (the evaluation drives), as the node would run them
        try:
            config = OdometryConfig.from_flat(result_to_parameters(result, allow_invalid=True))
            if isinstance(done['filter'], Exception):
                raise done['filter']
            r_floor, r_rel, count = done['filter']
            gyro = replace(gyro, r_floor=r_floor, r_rel=r_rel, r_intervals=count)
            config = replace(config, values={**config.values, **gyro_parameters(gyro)})
            scale, windows = fit_adapt_yaw_scale(config, evaluate, eval_seg,
                                                 _jobs(result.options.jobs))
            gyro = replace(gyro, adapt_yaw_scale=scale, scale_windows=windows)
        except (DataError, FitError, ParameterError) as err:
            result = replace(result, warnings=result.warnings + (
                f"gyro filter noise not (fully) calibrated (adapt's keeps the defaults it did "
                f'not fit): {err}',))
        result = replace(result, gyro=gyro)
    if plain:
        result = _add_plain_reference(result, train, evaluate, done.get('plain'))
    return result


def _tail_task(task: str, result: CalibrationResult, train: Sequence[Drive],
               evaluate: Sequence[Drive]):
    """Run one of :func:`_add_gyro`'s parallel tasks; an expected error is returned, not raised."""
    if task == 'plain':
        return _plain_fit(result, train)
    try:
        bare = replace(result, noise={})   # the covariance is not what the filter noise fits
        return fit_filter_noise(OdometryConfig.from_flat(result_to_parameters(
            bare, allow_invalid=True)), evaluate)
    except (DataError, FitError, ParameterError) as err:
        return err


_GYRO_TASK = '(gyro)'


def _fit_gyro_outcome(train: Sequence[Drive]) -> GyroFit | str:
    """Return the gyro fit on the training drives, or why there is none."""
    try:
        return fit_gyro(train)
    except (DataError, FitError) as err:
        return str(err)


def _jobs(jobs: int) -> int:
    return usable_cpus() if jobs <= 0 else jobs
