"""Atomic file output: write to a temporary file beside the target, then rename.

A reader never sees half a file, an interrupted write leaves the old file untouched, and an
existing file is only replaced when the caller says ``force``.
"""

from __future__ import annotations

import os
from pathlib import Path
import tempfile
from typing import Union

from skidkin_ros.errors import OutputError

__all__ = ['atomic_write_text', 'atomic_write_bytes', 'check_writable']

PathLike = Union[str, os.PathLike]


def check_writable(path: PathLike, force: bool) -> Path:
    """Fail early (before long work) if ``path`` exists without force or its folder is missing."""
    target = Path(path)
    if target.exists() and not force:
        raise OutputError(f'{target} already exists; pass --force to overwrite it')
    parent = target.parent if str(target.parent) else Path('.')
    if not parent.is_dir():
        raise OutputError(f'folder {parent} does not exist; create it or choose another --out')
    if not os.access(parent, os.W_OK):
        raise OutputError(f'folder {parent} is not writable; choose another --out')
    return target


def atomic_write_bytes(path: PathLike, data: bytes, force: bool = False) -> Path:
    target = check_writable(path, force)
    fd, tmp = tempfile.mkstemp(prefix=f'.{target.name}.', suffix='.tmp', dir=target.parent)
    try:
        with os.fdopen(fd, 'wb') as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        if not force and target.exists():
            raise OutputError(f'{target} appeared while writing; pass --force to overwrite it')
        os.replace(tmp, target)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return target


def atomic_write_text(path: PathLike, text: str, force: bool = False) -> Path:
    return atomic_write_bytes(path, text.encode('utf-8'), force)
