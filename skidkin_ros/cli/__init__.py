"""The ``skidkin`` command line (the only place that prints for users)."""
