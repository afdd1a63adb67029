"""Calibration: segments, one least-squares engine, fitting, evaluation, noise, the diagnosis."""

import sys

from skidkin_ros.core.calibration import gyro_fit

# The gyro fit's former module name (core/calibration/imu.py), kept only for the lab's studies
# that still import it under that name: delete these lines once they import gyro_fit.
sys.modules.setdefault(__name__ + '.imu', gyro_fit)
