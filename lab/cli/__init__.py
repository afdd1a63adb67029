"""The lab's command: the studies behind docs/results.md (``python -m lab.cli --help``)."""
