"""The ``skidkin`` command line (the only place that prints for users)."""

# The modules of this package (the API is theirs; ``skidkin_ros`` re-exports the public part).
__all__ = [
    'cmd_calibrate',
    'cmd_demo',
    'cmd_diagnose',
    'cmd_evaluate',
    'cmd_groundtruth',
    'cmd_models',
    'cmd_predict',
    'cmd_simulate',
    'commands',
    'common',
    'main',
    'progress',
    'tables',
]
