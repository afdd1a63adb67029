"""Calibration: segments, one least-squares engine, fitting, evaluation, noise, the diagnosis."""

# The modules of this package (the API is theirs; ``skidkin_ros`` re-exports the public part).
__all__ = [
    'diagnosis',
    'engine',
    'evaluation',
    'fitting',
    'gyro_fit',
    'gyro_windows',
    'holdout',
    'noise_fit',
    'noise_notes',
    'pipeline',
    'predictor',
    'results',
    'segments',
    'selection',
    'steps',
    'weighting',
]
