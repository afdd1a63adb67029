"""Calibration report: the paper's figures from the user's data and a Markdown page."""

from typing import Any

__all__ = ['write_report']


def __getattr__(name: str) -> Any:
    # write_report needs matplotlib; import it only when used (the CLI imports report.diagnosis)
    if name == 'write_report':
        from skidkin_ros.report.page import write_report
        return write_report
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
