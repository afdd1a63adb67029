"""Online calibration: the active model's parameters learned from a reference while driving."""

from skidkin_ros.core.online.attach import attach_online, online_odometer
from skidkin_ros.core.online.calibrator import MAX_STEPS, OnlineCalibrator, STATES
from skidkin_ros.core.online.grounds import Ground

__all__ = ['OnlineCalibrator', 'Ground', 'MAX_STEPS', 'STATES', 'attach_online',
           'online_odometer',
           # the modules the calibrator is made of
           'calibrator', 'gates', 'grounds', 'window']
