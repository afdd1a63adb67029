"""Calibration report: the paper's figures from the user's data and a Markdown page."""

from skidkin_ros.report.page import write_report

__all__ = ['write_report']
