"""Calibration: segments, one least-squares engine, fitting, evaluation, noise, the diagnosis."""
