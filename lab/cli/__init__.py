"""The lab's command: the studies behind docs/results.md (``python -m lab.cli --help``)."""

__all__ = ['cmd_effects', 'cmd_estimate', 'cmd_imu_study', 'main']
