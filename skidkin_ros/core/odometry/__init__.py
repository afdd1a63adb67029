"""Odometry: what the node runs on every wheel sample, and offline prediction by the same code.

The integrator, the process-noise model, covariance propagation and the node's configuration.
"""
