"""Estimation: a reference EKF and the NEES checks of whether a covariance is honest."""
