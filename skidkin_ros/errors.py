"""The one error hierarchy of skidkin_ros.

Every message says what was expected (with units) and what to do about it.
"""

from __future__ import annotations

__all__ = [
    'SkidkinError',
    'ConfigError',
    'ParameterError',
    'DataError',
    'RecordingError',
    'FitError',
    'OutputError',
    'brief',
]

# Longest text of a user's value echoed in a message: a parameter given as a list of a million
# numbers must not make a message of megabytes.
BRIEF_CHARS = 120


def brief(value: object, limit: int = BRIEF_CHARS) -> str:
    """Return ``repr(value)`` cut to about ``limit`` characters, saying how long it was."""
    text = repr(value)
    if len(text) <= limit:
        return text
    return f'{text[:limit]}... ({len(text)} characters in all)'


class SkidkinError(Exception):
    """Base class of every error raised on purpose by skidkin_ros."""

    exit_code = 1


class ConfigError(SkidkinError):
    """A configuration or parameters file is missing, unreadable or of the wrong schema."""

    exit_code = 2


class ParameterError(ConfigError):
    """A parameter value is out of range, non-finite, of the wrong type, or unknown."""


class DataError(SkidkinError):
    """Input data is unusable: too short, no motion, no overlap, bad values."""

    exit_code = 3


class RecordingError(DataError):
    """A recording (rosbag2 or table) cannot be opened or decoded."""


class FitError(SkidkinError):
    """A fit did not converge, sits on a bound, or is not observable from the data."""

    exit_code = 4


class OutputError(SkidkinError):
    """An output cannot be written (exists without --force, unwritable folder)."""

    exit_code = 5
