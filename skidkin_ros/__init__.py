"""skidkin_ros: calibrated skid-steer wheel odometry (ROS-free core, adapters, node, CLI).

The public API, for an estimator or a planner author (docs/api.md has a runnable example):

* :func:`load_parameters` (= ``OdometryConfig.from_file``): read and validate a parameters file
  written by ``skidkin calibrate`` or ``skidkin diagnose`` (or by hand);
* :class:`Odometer`: the object the node runs on every wheel sample; ``Odometer.from_config``
  builds it from a file, ``step``/``update`` take one sample, ``predict`` a whole drive
  (:class:`WheelSamples` in, :class:`Prediction` out: poses, twists and the published
  covariance after every sample);
* :func:`predict` and :func:`predict_track`: the prediction step of a filter, the pose and its
  covariance carried from one stamp to another over the wheel samples between, with the same
  covariance the node publishes (:class:`PoseCovariancePropagator`).

Everything else is importable from its module and may change between releases.
"""

__version__ = '0.1.0'

# After __version__: the modules below read it while this package is still being imported.
from skidkin_ros.core.drive import WheelSamples  # noqa: E402
from skidkin_ros.core.kinematics.models import get_model, MODELS  # noqa: E402
from skidkin_ros.core.kinematics.specs import Geometry  # noqa: E402
from skidkin_ros.core.odometry.config import OdometryConfig  # noqa: E402
from skidkin_ros.core.odometry.noise import NoiseModel  # noqa: E402
from skidkin_ros.core.odometry.odometer import Odometer, Prediction  # noqa: E402
from skidkin_ros.core.odometry.propagation import (PoseCovariancePropagator, predict,  # noqa: E402
                                                   predict_track)
from skidkin_ros.errors import SkidkinError  # noqa: E402

load_parameters = OdometryConfig.from_file

__all__ = [
    '__version__',
    'Geometry',
    'MODELS',
    'NoiseModel',
    'Odometer',
    'OdometryConfig',
    'PoseCovariancePropagator',
    'Prediction',
    'SkidkinError',
    'WheelSamples',
    'get_model',
    'load_parameters',
    'predict',
    'predict_track',
]
