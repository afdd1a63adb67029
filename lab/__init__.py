"""The lab: studies, their commands, benchmarks and the docs generator.

Runnable from a clone of the repository (``python -m lab.cli --help``, ``make bench``,
``make docs``); never installed and never imported by the ``skidkin_ros`` package.
"""

__all__ = ['cli', 'docs', 'report', 'studies']
