"""Open a recording: storage files, damaged metadata, message types (C1-C3, C6).

A rosbag2 (folder, .db3 or .mcap) is read with rosbags' rosbag2 Reader and decoded as CDR with
the ROS 2 Jazzy type store plus the definitions stored in the bag. A ROS 1 ``.bag`` (or a folder
of split .bag files) is read with rosbags' rosbag1 Reader and decoded as ROS 1 with a type store
built from the definitions the bag holds, as rosbags' AnyReader builds it, but topic by topic:
one connection whose definition is missing, unparsable or whose md5 disagrees is only refused
when its topic is read (C6), not for the whole bag. A definition missing from the bag falls back
to ROS 1 Noetic's when its md5 matches. The readers above this one see the same connections and
the same decoded field names either way, so the same drive gives the same numbers.
"""

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
from rosbags.rosbag1 import Reader as Reader1
from rosbags.rosbag1 import ReaderError as ReaderError1
from rosbags.rosbag2 import Reader
from rosbags.rosbag2.errors import ReaderError
from rosbags.typesys import get_types_from_msg, get_typestore, Stores
from rosbags.typesys.store import Typestore

from skidkin_ros.adapters.bags.common import (DEFAULT_MAX_CORRUPT, METADATA_ERRORS, MetadataError,
                                              ROS1_SUFFIX, storage_remedy, STORAGE_SUFFIXES)
from skidkin_ros.errors import RecordingError

LOG = logging.getLogger(__name__)

# ROS 1 Noetic's store lacks tf2_msgs; its TFMessage is this (the same md5 as ROS 1's).
_TF2_MSGS_ROS1 = 'geometry_msgs/TransformStamped[] transforms'
_OPEN_ERRORS = (ReaderError, ReaderError1, apsw.Error, sqlite3.Error, OSError, struct.error,
                ValueError, OverflowError, KeyError, IndexError, EOFError, TypeError)


def ros1_fallback_store() -> Typestore:
    """Return ROS 1 Noetic's type store with tf2_msgs/TFMessage added."""
    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg(_TF2_MSGS_ROS1, 'tf2_msgs/msg/TFMessage'))
    return store


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
        # 'rosbag2' or 'rosbag1': how the storage is read and the messages decoded.
        self.format = 'rosbag2'
        # Message types of a ROS 1 bag that cannot be decoded, with the reason (C6).
        self._undecodable: dict[str, str] = {}
        self._readers: list[Any] = []
        self.files: list[Path] = []
        self._msg_files = [Path(f) for f in msg_files]
        for msg_file in self._msg_files:
            self._register_msg_file(msg_file)
        self._open()

    # -- opening ---------------------------------------------------------------------------------
    def _storage_files(self) -> tuple[list[Path], bool]:
        """Return the paths to open with rosbags and whether they are bare storage files."""
        path = self.path
        if not path.exists():
            raise RecordingError(f'recording {path} does not exist; expected a rosbag2 folder '
                                 '(with metadata.yaml), a .db3 / .mcap file or a ROS 1 .bag')
        if path.is_file() and path.name == 'metadata.yaml':
            path = self.path = path.parent
        if not path.is_file() and not path.is_dir():
            raise RecordingError(f'{path} is neither a file nor a folder (a device or a pipe?); '
                                 'expected a rosbag2 folder or a .db3 / .mcap file')
        if path.is_file():
            if path.suffix == ROS1_SUFFIX:
                self.format = 'rosbag1'
                return [path], True
            if path.suffix not in STORAGE_SUFFIXES:
                raise RecordingError(f'{path} is not a rosbag2 recording nor a ROS 1 bag; '
                                     'expected a folder with metadata.yaml, a .db3 / .mcap file '
                                     'or a .bag file')
            return [path], True
        if (path / 'metadata.yaml').is_file():
            return [path], False
        found = sorted(p for p in path.iterdir() if p.suffix in STORAGE_SUFFIXES and p.is_file())
        if not found:
            bags = sorted(p for p in path.iterdir() if p.suffix == ROS1_SUFFIX and p.is_file())
            if bags:
                self.format = 'rosbag1'
                self.notes.append(f'{path}: reading its {len(bags)} ROS 1 bag file(s) as one '
                                  f'recording ({", ".join(p.name for p in bags)})')
                return bags, True
            present = sorted(p.name for p in path.iterdir())[:10]
            raise RecordingError(f'{path} has no metadata.yaml and no .db3 / .mcap / .bag files '
                                 f'(found {present}); point to a rosbag2 folder or file, or a '
                                 'ROS 1 .bag')
        self.notes.append(f'{path} has no metadata.yaml: reading {len(found)} storage file(s) '
                          f'directly ({", ".join(p.name for p in found)}); run `ros2 bag '
                          'reindex` to restore the metadata')
        return found, True

    def _open_one(self, target: Path) -> Any:
        if self.format == 'rosbag1':
            return self._open_ros1(target)
        files = ([target] if target.is_file()
                 else sorted(p for p in target.iterdir() if p.suffix in STORAGE_SUFFIXES))
        try:
            reader = Reader(target)
            reader.open()  # reads metadata.yaml of a folder, then the storage
        except _OPEN_ERRORS as err:
            if target.is_dir() and str(err).startswith(METADATA_ERRORS):
                raise MetadataError(' '.join(str(err).split())) from err
            names = ', '.join(str(f) for f in files) or str(target)
            remedy = storage_remedy(files[0]) if files else 'check the recording'
            raise RecordingError(f'cannot open recording {names}: {err} -- {remedy}') from err
        return reader

    def _open_ros1(self, target: Path) -> Reader1:
        try:
            reader = Reader1(target)
            reader.open()  # reads the index (connections and chunk infos) at the end
        except _OPEN_ERRORS as err:
            raise RecordingError(
                f'cannot open ROS 1 bag {target}: {" ".join(str(err).split())} -- a bag still '
                f'being recorded (.bag.active) or cut short has no index: run `rosbag reindex '
                f'{target}` on a ROS 1 machine, then read the reindexed bag') from err
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
        if self.format == 'rosbag1':
            self._register_ros1_types()
            return
        if bare and len(targets) == 1 and self.path.is_file():
            self.notes.append(f'reading storage file {self.path} directly (no metadata.yaml)')
        self._register_bag_types()

    def _open_without_metadata(self, err: MetadataError) -> tuple[list[Any], list[Path]]:
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
            # rosbag2's Reader says is_open; rosbag1's holds its file in bio while open.
            if getattr(reader, 'is_open', getattr(reader, 'bio', None) is not None):
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

    def _register_ros1_types(self) -> None:
        """Build the ROS 1 type store from the bag's definitions, one connection at a time.

        As rosbags' AnyReader does, but a definition that is missing, cannot be parsed, clashes
        with another or whose md5 disagrees makes its type undecodable (refused when its topic
        is read, naming the reason), not the whole bag unreadable.
        """
        self.typestore = get_typestore(Stores.EMPTY)
        fallback = ros1_fallback_store()
        for conn in self._connections():
            if conn.msgtype in self.typestore.fielddefs or conn.msgtype in self._undecodable:
                continue
            reason = self._register_ros1_connection(conn, fallback)
            if reason is not None:
                self._undecodable[conn.msgtype] = reason
                LOG.warning('%s on %s: %s', conn.msgtype, conn.topic, reason)
        for msg_file in self._msg_files:
            self._register_msg_file(msg_file)
            self._undecodable.pop(f'{msg_file.parent.parent.name}/msg/{msg_file.stem}', None)
        if self.path.is_file():
            self.notes.append(f'reading ROS 1 bag {self.path}')

    def _register_ros1_connection(self, conn: Connection, fallback: Typestore) -> str | None:
        """Register one connection's type; return why it cannot be decoded, or None."""
        text = conn.msgdef.data if conn.msgdef.format == MessageDefinitionFormat.MSG else ''
        if not text.strip():
            if conn.msgtype in fallback.fielddefs:
                definition, md5 = fallback.generate_msgdef(conn.msgtype)
                if not conn.digest or md5 == conn.digest:
                    self.typestore.register(get_types_from_msg(definition, conn.msgtype))
                    self.notes.append(f'{conn.topic}: the bag stores no definition of '
                                      f"{conn.msgtype}; its md5 matches ROS 1 Noetic's, used")
                    return None
            return 'the bag stores no message definition for it'
        try:
            self.typestore.register(get_types_from_msg(text, conn.msgtype))
        except Exception as err:  # noqa: B902 - rosbags' parser raises several kinds
            return f'its stored definition cannot be used ({" ".join(str(err).split())})'
        md5 = self.typestore.generate_msgdef(conn.msgtype)[1]
        if conn.digest and md5 != conn.digest:
            return (f'its stored definition does not match its md5 ({conn.digest}, the '
                    f'definition gives {md5})')
        return None

    def _deserialize(self, raw: bytes, msgtype: str) -> Any:
        """Decode one message: CDR for rosbag2, the ROS 1 wire format for a .bag."""
        if self.format == 'rosbag1':
            return self.typestore.deserialize_ros1(raw, msgtype)
        return self.typestore.deserialize_cdr(raw, msgtype)

    def _require_type(self, topic: str, msgtype: str) -> None:
        if self.format == 'rosbag1' and (msgtype in self._undecodable
                                         or msgtype not in self.typestore.fielddefs):
            reason = self._undecodable.get(msgtype, 'the bag holds no definition for it')
            raise RecordingError(
                f'topic {topic} of ROS 1 bag {self.path} has type {msgtype}, which cannot be '
                f'decoded: {reason}. Supply its ROS 1 .msg file (on the command line --msg-file '
                f'.../{msgtype}.msg; open_recording(path, msg_files=)), '
                'or name another topic')
        if msgtype not in self.typestore.fielddefs:
            raise RecordingError(
                f'topic {topic} has type {msgtype}, which is not a ROS 2 Jazzy type and has no '
                'definition stored in the bag; supply its .msg file (open_recording(path, '
                f'msg_files=[".../{msgtype}.msg"]), on the command line --msg-file) or '
                'record with a rosbag2 that stores message definitions')

    # -- topics ----------------------------------------------------------------------------------
    def _connections(self) -> list[Connection]:
        return [c for r in self._readers for c in r.connections]
