"""Studies: simulated experiments whose results docs/results.md reports (they return data)."""

__all__ = ['effects', 'estimation', 'imu']
