"""Odometry: what the node runs on every wheel sample, and offline prediction by the same code.

The odometer (stamp rules, wheel pairing, integration, covariance, what is published), the wheel
rules shared with the bag reader, the integrator, the process-noise model, covariance propagation
and the node's configuration.
"""

# The modules of this package (the API is theirs; ``skidkin_ros`` re-exports the public part).
__all__ = [
    'config',
    'controller',
    'gyro',
    'gyro_buffer',
    'gyro_filter',
    'gyro_params',
    'integrator',
    'interval',
    'noise',
    'odometer',
    'params_file',
    'pose_limits',
    'prediction',
    'propagation',
    'reference',
    'schema',
    'se2',
    'uncertainty',
    'wheels',
]
