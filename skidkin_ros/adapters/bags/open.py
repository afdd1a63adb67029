"""Open a recording: storage files, damaged metadata, message types (C1-C3, C6)."""

from __future__ import annotations

from collections import Counter
import logging
from pathlib import Path
import sqlite3
import struct
from types import TracebackType
from typing import Any, Sequence

import apsw
from rosbags.interfaces import Connection, MessageDefinitionFormat
from rosbags.rosbag2 import Reader
from rosbags.rosbag2.errors import ReaderError
from rosbags.typesys import get_types_from_msg, get_typestore, Stores

from skidkin_ros.adapters.bags.common import (DEFAULT_MAX_CORRUPT, METADATA_ERRORS, MetadataError,
                                              storage_remedy, STORAGE_SUFFIXES)
from skidkin_ros.errors import RecordingError

LOG = logging.getLogger(__name__)


class BagStorage:
    """The storage side of a recording: its readers, connections and type store."""

    def __init__(self, path: Path | str, *, max_corrupt: int = DEFAULT_MAX_CORRUPT,
                 msg_files: Sequence[Path | str] = ()) -> None:
        self.path = Path(path)
        self.max_corrupt = int(max_corrupt)
        self.notes: list[str] = []
        self.counts: Counter[tuple[str, str]] = Counter()
        # The wheel input actually used by the last read_wheels(), as node parameters (input,
        # left/right_wheel_joints) plus the topics: what a parameters file records.
        self.wheel_input: dict[str, Any] = {}
        self.typestore = get_typestore(Stores.ROS2_JAZZY)
        self._readers: list[Reader] = []
        self.files: list[Path] = []
        for msg_file in msg_files:
            self._register_msg_file(Path(msg_file))
        self._open()

    # -- opening ---------------------------------------------------------------------------------
    def _storage_files(self) -> tuple[list[Path], bool]:
        """Return the paths to open with rosbags and whether they are bare storage files."""
        path = self.path
        if not path.exists():
            raise RecordingError(f'recording {path} does not exist; expected a rosbag2 folder '
                                 '(with metadata.yaml) or a .db3 / .mcap file')
        if path.is_file() and path.name == 'metadata.yaml':
            path = self.path = path.parent
        if not path.is_file() and not path.is_dir():
            raise RecordingError(f'{path} is neither a file nor a folder (a device or a pipe?); '
                                 'expected a rosbag2 folder or a .db3 / .mcap file')
        if path.is_file():
            if path.suffix not in STORAGE_SUFFIXES:
                raise RecordingError(f'{path} is not a rosbag2 recording; expected a folder with '
                                     'metadata.yaml or a .db3 / .mcap file')
            return [path], True
        if (path / 'metadata.yaml').is_file():
            return [path], False
        found = sorted(p for p in path.iterdir() if p.suffix in STORAGE_SUFFIXES and p.is_file())
        if not found:
            present = sorted(p.name for p in path.iterdir())[:10]
            raise RecordingError(f'{path} has no metadata.yaml and no .db3 / .mcap files '
                                 f'(found {present}); point to a rosbag2 folder or file')
        self.notes.append(f'{path} has no metadata.yaml: reading {len(found)} storage file(s) '
                          f'directly ({", ".join(p.name for p in found)}); run `ros2 bag '
                          'reindex` to restore the metadata')
        return found, True

    def _open_one(self, target: Path) -> Reader:
        files = ([target] if target.is_file()
                 else sorted(p for p in target.iterdir() if p.suffix in STORAGE_SUFFIXES))
        errors = (ReaderError, apsw.Error, sqlite3.Error, OSError, struct.error, ValueError,
                  OverflowError, KeyError, IndexError, EOFError, TypeError)
        try:
            reader = Reader(target)
            reader.open()  # reads metadata.yaml of a folder, then the storage
        except errors as err:
            if target.is_dir() and str(err).startswith(METADATA_ERRORS):
                raise MetadataError(' '.join(str(err).split())) from err
            names = ', '.join(str(f) for f in files) or str(target)
            remedy = storage_remedy(files[0]) if files else 'check the recording'
            raise RecordingError(f'cannot open recording {names}: {err} -- {remedy}') from err
        return reader

    def _open(self) -> None:
        targets, bare = self._storage_files()
        try:
            readers = [self._open_one(target) for target in targets]
        except MetadataError as err:
            readers, targets = self._open_without_metadata(err)
        except RecordingError:
            self.close()
            raise
        self.files = [f for t in targets for f in ([t] if t.is_file() else
                      sorted(p for p in t.iterdir() if p.suffix in STORAGE_SUFFIXES))]
        self._readers = sorted(readers, key=lambda r: r.start_time if r.message_count else 0)
        if bare and len(targets) == 1 and self.path.is_file():
            self.notes.append(f'reading storage file {self.path} directly (no metadata.yaml)')
        self._register_bag_types()

    def _open_without_metadata(self, err: MetadataError) -> tuple[list[Reader], list[Path]]:
        """Read a folder whose metadata.yaml is broken from its storage files (C1)."""
        folder = self.path
        files = sorted(p for p in folder.iterdir() if p.suffix in STORAGE_SUFFIXES and p.is_file())
        if not files:
            raise RecordingError(f'{folder}/metadata.yaml cannot be read ({err}) and the folder '
                                 'has no .db3 / .mcap file; point to a rosbag2 recording') from err
        try:
            readers = [self._open_one(f) for f in files]
        except RecordingError as inner:
            self.close()
            raise RecordingError(f'{folder}/metadata.yaml cannot be read ({err}), and reading the '
                                 f'storage files directly failed too: {inner}') from inner
        self.notes.append(f'{folder}/metadata.yaml cannot be read ({err}); reading its '
                          f'{len(files)} storage file(s) directly. The storage files are not at '
                          f'fault: run `ros2 bag reindex {folder}` to rewrite the metadata')
        return readers, files

    def close(self) -> None:
        """Close the storage files."""
        readers, self._readers = self._readers, []
        for reader in readers:
            if reader.is_open:
                reader.close()

    def __enter__(self) -> 'BagStorage':
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.close()

    # -- types (C6) ------------------------------------------------------------------------------
    def _register_msg_file(self, path: Path) -> None:
        # The type name comes from the path: <package>/msg/<Name>.msg.
        if not path.is_file() or path.suffix != '.msg' or path.parent.name != 'msg':
            raise RecordingError(f'message definition {path} not found or not named '
                                 '<package>/msg/<Name>.msg')
        msgtype = f'{path.parent.parent.name}/msg/{path.stem}'
        try:
            self.typestore.register(get_types_from_msg(path.read_text(), msgtype))
        except Exception as err:  # noqa: B902 - rosbags' parser raises several kinds
            raise RecordingError(f'cannot parse message definition {path}: {err}') from err

    def _register_bag_types(self) -> None:
        known = self.typestore.fielddefs
        for conn in self._connections():
            if conn.msgtype in known or conn.msgdef.format == MessageDefinitionFormat.NONE:
                continue
            if not conn.msgdef.data.strip():
                continue
            try:
                if conn.msgdef.format == MessageDefinitionFormat.MSG:
                    self.typestore.register(get_types_from_msg(conn.msgdef.data, conn.msgtype))
            except Exception as err:  # noqa: B902 - a broken definition must not block others
                LOG.warning('cannot parse the definition of %s stored in the bag: %s',
                            conn.msgtype, err)

    def _require_type(self, topic: str, msgtype: str) -> None:
        if msgtype not in self.typestore.fielddefs:
            raise RecordingError(
                f'topic {topic} has type {msgtype}, which is not a ROS 2 Jazzy type and has no '
                'definition stored in the bag; supply its .msg file (open_recording(path, '
                f'msg_files=[".../{msgtype}.msg"]), on the command line --msg-file) or '
                'record with a rosbag2 that stores message definitions')

    # -- topics ----------------------------------------------------------------------------------
    def _connections(self) -> list[Connection]:
        return [c for r in self._readers for c in r.connections]
