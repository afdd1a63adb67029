"""Make an odometer learn online: the one place the node and ``skidkin predict`` build it."""

from __future__ import annotations

import collections
import functools
import math
from typing import Callable

import numpy as np

from skidkin_ros.core.kinematics.augmented import AUGMENTED_NAME
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.gyro import GyroStatus
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.core.odometry.saved_grounds import saved_grounds
from skidkin_ros.core.online.augmented import AugmentedCalibrator, LayoutModel, online_layout
from skidkin_ros.core.online.calibrator import OnlineCalibrator
from skidkin_ros.core.online.remembered import remember

__all__ = ['attach_online', 'online_odometer', 'make_calibrator']


def make_calibrator(config: OdometryConfig,
                    counters: collections.Counter[str] | None = None,
                    warn: Callable[..., None] | None = None) -> OnlineCalibrator:
    """Return the online calibrator a configuration describes (online.enabled or not).

    It starts from the file's parameters of the active model; their covariance
    (models.<m>.parameter_covariance), when the file has one, is the first ground's information
    on top of the broad prior (online.prior_sigma). An augmented model learns its base model's
    parameters and its extensions' fitted ones (:mod:`skidkin_ros.core.online.augmented`).
    The file's remembered grounds (``online.grounds.*``) are known from the start.
    """
    if config.model == AUGMENTED_NAME:
        layout = online_layout(config.augmented_base, config.geometry,
                               config.model_values[config.augmented_base],
                               config.augmented_values, config.augmented_extensions)
        augmented = LayoutModel(layout)
        learner = AugmentedCalibrator(augmented, augmented.mapping(layout.vector()),
                                      config.geometry, config.active_noise, config.online,
                                      config['interval'], None, counters, warn)
        # a residual model's coefficients are held: their file covariance is carried as is
        learner.coefficient_covariance = config.residual_coefficient_covariance()
    else:
        model = get_model(config.model)
        flat = config.values.get(f'models.{model.name}.parameter_covariance')
        size = len(model.params)
        prior = None if flat is None else np.asarray(flat, dtype=float).reshape(size, size)
        learner = OnlineCalibrator(model, config.model_values[model.name], config.geometry,
                                   config.active_noise, config.online, config['interval'],
                                   prior, counters, warn)
    saved = saved_grounds(config.values, config.geometry)
    if saved is not None:   # the grounds a saved calibration remembered (remembered.py)
        remember(learner, saved)
    return learner


def attach_online(odometer: Odometer, config: OdometryConfig,
                  warn: Callable[..., None] | None = None) -> OnlineCalibrator | None:
    """Attach a new calibrator when online.enabled, else detach any; return it (or None)."""
    learner = None
    if config.online.enabled:
        learner = make_calibrator(config, odometer.counters, warn)
        # the gyro, when there is one (imu.mode fuse), judges the reference's heading
        learner.gyro_turn = functools.partial(_gyro_turn, odometer)
        learner.gyro_noise = (config.imu.arw, config.imu.bias_sigma)
    odometer.attach_learner(learner)
    return learner


def _gyro_turn(odometer: Odometer, t_a_ns: int, t_b_ns: int) -> float | None:
    """Return the gyro's yaw (rad) over a wheel-time interval.

    None: no gyro (imu.mode off), or an empty interval; NaN: a gyro whose buffer does not
    cover the interval (poses farther apart than the buffer's few seconds).
    """
    gyro = odometer.gyro
    if gyro is None or t_b_ns <= t_a_ns:
        return None
    status, mean = gyro.buffer.mean_rate(t_a_ns, t_b_ns)
    return mean * ((t_b_ns - t_a_ns) * 1e-9) if status is GyroStatus.COVERED else math.nan


def online_odometer(config: OdometryConfig, **kwargs) -> Odometer:
    """Return ``Odometer.from_config(config, **kwargs)``, learning online when enabled."""
    odometer = Odometer.from_config(config, **kwargs)
    if config.online.enabled:
        attach_online(odometer, config, kwargs.get('warn'))
    return odometer
