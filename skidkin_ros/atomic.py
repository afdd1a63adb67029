"""File output, the one home for writing files: checked first, written whole, with the right mode.

1. Check before any long work (:func:`check_writable`, :func:`check_writable_dir`): an existing
   output needs ``force``; a folder, a device or a name longer than the file system takes is
   refused; the folder must exist and really take a file (a probe file is created and removed:
   permission bits alone do not tell, e.g. for root or on a read-only file system).
2. Write to a temporary file beside the target, flush it to disk, then rename it over the target
   (:func:`atomic_write_bytes`): a reader never sees half a file, and an interrupted write leaves
   the old file untouched.
3. Give the file the mode the user expects: a new file gets 0666 less the umask, as ``open``
   would give it (a temporary file is created 0600, which another user, e.g. the node's, could
   not read); a replaced file keeps its mode.

Every failure is an :class:`~skidkin_ros.errors.OutputError` (exit code 5) naming the path.
"""

from __future__ import annotations

import os
from pathlib import Path
import stat
import tempfile
from typing import Union

from skidkin_ros.errors import OutputError

__all__ = ['atomic_write_text', 'atomic_write_bytes', 'check_writable', 'check_writable_dir',
           'new_file_mode']

PathLike = Union[str, os.PathLike]
# Characters of the target name kept in the temporary name (which adds about 14).
_TMP_NAME_CHARS = 40


def new_file_mode() -> int:
    """Return the mode ``open`` gives a new file: 0666 less the process umask."""
    try:
        with open('/proc/self/status', encoding='ascii') as status:
            for line in status:
                if line.startswith('Umask:'):
                    return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)  # no way to read it without setting it elsewhere
    os.umask(mask)
    return 0o666 & ~mask


def _name_max(folder: Path) -> int:
    try:
        return os.pathconf(folder, 'PC_NAME_MAX')
    except (OSError, ValueError):
        return 255


def _probe(folder: Path, what: str) -> None:
    """Create and remove a file in ``folder``, or raise OutputError saying why it cannot."""
    try:
        fd, probe = tempfile.mkstemp(prefix='.skidkin-probe.', dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise OutputError(f'cannot write in folder {folder} ({err.strerror or err}); choose '
                          f'another {what}') from err


def check_writable(path: PathLike, force: bool, what: str = '--out') -> Path:
    """Fail early (before long work) if ``path`` cannot be written as a file; return it."""
    target = Path(path)
    if not target.name or target.name in ('.', '..'):
        raise OutputError(f'{target} is not a file name; give {what} a file path')
    parent = target.parent if str(target.parent) else Path('.')
    if len(os.fsencode(target.name)) > _name_max(parent if parent.is_dir() else Path('.')):
        raise OutputError(f'the name {target.name[:40]}... ({len(target.name)} characters) is '
                          f'longer than the file system takes; choose a shorter {what}')
    if target.is_dir():
        raise OutputError(f'{target} is a folder; give {what} a file path (e.g. '
                          f'{target / "params.yaml"})')
    if target.exists():
        if not target.is_file():
            raise OutputError(f'{target} exists and is not a regular file (a device or a '
                              f'pipe?); choose another {what}')
        if not force:
            raise OutputError(f'{target} already exists; pass --force to overwrite it')
    if not parent.is_dir():
        kind = 'is not a folder' if parent.exists() else 'does not exist'
        raise OutputError(f'folder {parent} {kind}; create it or choose another {what}')
    _probe(parent, what)
    return target


def check_writable_dir(path: PathLike, force: bool, what: str = '--report') -> Path:
    """Fail early if ``path`` cannot be an output folder (a file, not empty without force)."""
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise OutputError(f'{folder} exists and is not a folder; give {what} a folder path')
    if folder.is_dir():
        if not force and any(folder.iterdir()):
            raise OutputError(f'folder {folder} exists and is not empty; pass --force to '
                              'overwrite its files')
        _probe(folder, what)
        return folder
    ancestor = folder.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise OutputError(f'{ancestor} is not a folder; {folder} cannot be created there')
    _probe(ancestor, what)
    return folder


def atomic_write_bytes(path: PathLike, data: bytes, force: bool = False) -> Path:
    """Write ``data`` to ``path`` atomically (see the module docstring); return the path."""
    target = check_writable(path, force)
    try:
        mode = (stat.S_IMODE(target.stat().st_mode) if target.is_file() else new_file_mode())
        fd, tmp = tempfile.mkstemp(prefix=f'.{target.name[:_TMP_NAME_CHARS]}.', suffix='.tmp',
                                   dir=target.parent)
    except OSError as err:
        raise OutputError(f'cannot write {target}: {err.strerror or err}') from err
    try:
        with os.fdopen(fd, 'wb') as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
            os.fchmod(handle.fileno(), mode)
        if not force and target.exists():
            raise OutputError(f'{target} appeared while writing; pass --force to overwrite it')
        os.replace(tmp, target)
    except OSError as err:
        raise OutputError(f'cannot write {target}: {err.strerror or err}') from err
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return target


def atomic_write_text(path: PathLike, text: str, force: bool = False) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; return the path."""
    return atomic_write_bytes(path, text.encode('utf-8'), force)
