"""Calibration: segments, fitting, evaluation, hold-out, noise fitting and the diagnosis."""
