"""The per-chunk cache of lidar registrations: a recording's identity, chunk keys, npz files.

One job: step 3 of :mod:`skidkin_ros.adapters.lidar_chunks`. A key holds everything a chunk's
registration depends on (recording, topic, window, ICP settings, kiss-icp version); an
unreadable entry is recomputed and an unwritable folder only stops caching.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
from pathlib import Path
from typing import Any, Mapping, Union

import numpy as np

from skidkin_ros.adapters.lidar_gt import Registration
from skidkin_ros.adapters.lidar_plan import ChunkTask
from skidkin_ros.atomic import atomic_write_bytes
from skidkin_ros.errors import DataError, OutputError

__all__ = ['CACHE_VERSION', 'bag_identity', 'chunk_key']

# The chunked ground truth logs under one name, that of lidar_chunks, wherever the code lives.
_LOG = logging.getLogger('skidkin_ros.adapters.lidar_chunks')
CACHE_VERSION = 2


def bag_identity(path: Union[str, os.PathLike]) -> dict[str, Any]:
    """Return what identifies a recording for the cache: resolved path, sizes, mtimes, metadata.

    A bag folder contributes the hash of its metadata.yaml and the size and mtime of each storage
    file; a single file its size and mtime.
    """
    target = Path(path).resolve()
    if not target.exists():
        raise DataError(f'cannot identify recording {target}: it does not exist')
    files = sorted(p for p in target.iterdir() if p.is_file()) if target.is_dir() else [target]
    entries = []
    for item in files:
        stat = item.stat()
        entry = {'name': item.name, 'size': stat.st_size, 'mtime_ns': stat.st_mtime_ns}
        if item.name == 'metadata.yaml':
            entry['sha256'] = hashlib.sha256(item.read_bytes()).hexdigest()
        entries.append(entry)
    return {'path': str(target), 'files': entries}


def _kiss_version() -> str:
    try:
        from importlib.metadata import version
        return version('kiss-icp')
    except Exception:  # noqa: B902 - any failure: the key just says so
        return 'unknown'


def chunk_key(task: ChunkTask, identity: Mapping[str, Any]) -> str:
    """Return the cache key of a chunk: everything its registration depends on."""
    payload = {'version': CACHE_VERSION, 'kiss_icp': _kiss_version(), 'bag': identity,
               'topic': task.topic, 'window': [task.start_ns, task.stop_ns],
               'config': task.config.as_dict(),
               'grid': None if task.grid is None else [task.grid.origin_ns, task.grid.cell_ns]}
    text = json.dumps(payload, sort_keys=True, default=str)
    return hashlib.sha256(text.encode('utf-8')).hexdigest()


def _cache_path(cache_dir: Path, key: str) -> Path:
    return Path(cache_dir) / f'lidar_chunk_{key[:32]}.npz'


def _read_cached(path: Path, key: str) -> Registration | None:
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data['key']) != key:
                return None
            return Registration.from_arrays(data)
    except Exception as err:  # noqa: B902 - any unreadable cache is recomputed, never fatal
        _LOG.warning('ignoring unreadable ground-truth cache %s (%s); recomputing', path, err)
        return None


def _write_cached(path: Path, key: str, registration: Registration) -> str:
    """Cache one chunk; return why it could not be (a cache is a help, never a failure)."""
    buffer = io.BytesIO()
    np.savez(buffer, key=np.array(key), **registration.to_arrays())
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, buffer.getvalue(), force=True)
    except (OSError, OutputError) as err:
        return str(err)
    return ''
