"""Estimation: a reference EKF and the NEES checks of whether a covariance is honest."""

# The modules of this package (the API is theirs; ``skidkin_ros`` re-exports the public part).
__all__ = [
    'ekf',
    'nees',
]
