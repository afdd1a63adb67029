"""Stream messages one at a time, surviving storage errors and counting drops (C4, C5, C19)."""

from __future__ import annotations

import logging
from typing import Any, Iterator, Sequence

import numpy as np
from rosbags.interfaces import Connection

from skidkin_ros.adapters.bags.common import (DECODE_ERRORS, keep_monotonic, MAX_JUMP_NS,
                                              STORAGE_ERRORS, storage_remedy)
from skidkin_ros.errors import RecordingError

LOG = logging.getLogger(__name__)


class StreamMixin:
    """Streaming readers and the drop counts that go to ``notes``."""

    # -- streaming (C4, C19) ---------------------------------------------------------------------
    def _skip(self, what: str, reason: str, err: BaseException, skipped: int) -> int:
        skipped += 1
        self.counts[(what, reason)] += 1
        LOG.warning('%s: skipped a %s (%s)', what, reason, err)
        if skipped > self.max_corrupt:
            files = ', '.join(str(f) for f in self.files)
            raise RecordingError(
                f'{what}: more than {self.max_corrupt} corrupt messages or storage errors in '
                f'{files} (last: {err}); the recording is damaged -- '
                f'{storage_remedy(self.files[0]) if self.files else "re-record it"}') from err
        return skipped

    def _skip_cloud(self, topic: str, err: RecordingError, skipped: int, kept: int) -> int:
        """Count a cloud that decoded but cannot be used; past max_corrupt, say why."""
        skipped += 1
        self.counts[(topic, 'malformed cloud')] += 1
        LOG.warning('%s: skipped a malformed cloud (%s)', topic, err)
        if skipped > self.max_corrupt:
            raise RecordingError(
                f'lidar: {skipped} clouds on {topic} cannot be used ({kept} could), the last '
                f'because: {err}. The recording reads fine: its clouds do not hold what the '
                'lidar ground truth needs (fields x, y, z as float32 or float64, consistent '
                'with point_step and the data); check the driver, or name another --lidar-topic'
            ) from err
        return skipped

    def _raw_stream(self, connections: Sequence[Connection], what: str,
                    start_ns: int | None = None, stop_ns: int | None = None
                    ) -> Iterator[tuple[Connection, int, bytes]]:
        """Yield (connection, receive ns, raw bytes) in bag order, surviving storage errors."""
        skipped = 0
        for reader in self._readers:
            conns = [c for c in connections if c in reader.connections]
            if not conns:
                continue
            resume = start_ns
            jump_ns = 0
            while True:
                try:
                    for conn, t_ns, raw in reader.messages(conns, start=resume, stop=stop_ns):
                        resume = t_ns + 1
                        jump_ns = 0
                        yield conn, t_ns, raw
                    break
                except STORAGE_ERRORS as err:
                    if jump_ns == 0:
                        # A new incident (some progress since the last one): count it.
                        skipped = self._skip(what, 'storage error', err, skipped)
                        resume = resume if resume is not None else reader.start_time
                        jump_ns = 1
                    elif jump_ns > MAX_JUMP_NS:
                        raise RecordingError(
                            f'{what}: cannot read past a damaged part of {self.files[0]} '
                            f'({err}) -- {storage_remedy(self.files[0])}') from err
                    else:
                        # Still stuck at the damaged message: jump further ahead.
                        resume += jump_ns
                        jump_ns *= 2

    def messages(self, topic: str, start_ns: int | None = None, stop_ns: int | None = None
                 ) -> Iterator[tuple[int, Any]]:
        """Yield (receive ns, decoded message) of one topic, lazily, skipping corrupt ones."""
        for _, t_ns, msg in self.messages_of([topic], start_ns, stop_ns):
            yield t_ns, msg

    def messages_of(self, topics: Sequence[str], start_ns: int | None = None,
                    stop_ns: int | None = None) -> Iterator[tuple[str, int, Any]]:
        """Yield (topic, receive ns, decoded message) of several topics in recording order."""
        conns = [c for c in self._connections() if c.topic in topics]
        for topic in topics:
            if not any(c.topic == topic for c in conns):
                raise RecordingError(f'topic {topic} is not in {self.path}. Topics present: '
                                     f'{self._listing()}')
        for conn in conns:
            self._require_type(conn.topic, conn.msgtype)
        skipped = 0
        for conn, t_ns, raw in self._raw_stream(conns, ' + '.join(topics), start_ns, stop_ns):
            try:
                msg = self._deserialize(raw, conn.msgtype)
            except DECODE_ERRORS as err:
                skipped = self._skip(conn.topic, 'undecodable message', err, skipped)
                continue
            yield conn.topic, t_ns, msg

    def _drop(self, topic: str, reason: str, n: int = 1) -> None:
        if n:
            self.counts[(topic, reason)] += n

    def _note_drops(self, topic: str, kept: int) -> None:
        reasons = {reason: n for (t, reason), n in self.counts.items() if t == topic and n}
        if reasons:
            detail = ', '.join(f'{n} {reason}' for reason, n in sorted(reasons.items()))
            self.notes.append(f'{topic}: kept {kept} messages; skipped {detail}')

    def _reasons(self, topic: str) -> str:
        parts = [f'{n} {reason}' for (t, reason), n in self.counts.items() if t == topic]
        return ', '.join(parts) or (f'no message on {topic} could be read, though the recording '
                                    f'lists {self._count(topic)}')

    def _header_or_receive(self, topic: str, stamps: np.ndarray, receive: np.ndarray
                           ) -> np.ndarray:
        zero = stamps == 0
        if zero.all():
            self.notes.append(f'{topic}: every header.stamp is zero; using the bag receive time')
            return receive
        if zero.any():
            # A zero stamp among real ones is corrupt: push it out of order so it is dropped.
            stamps = stamps.copy()
            stamps[zero] = np.iinfo(np.int64).max
            self._drop(topic, 'zero stamp', int(zero.sum()))
            return stamps
        return stamps

    def _keep_in_order(self, topic: str, t: np.ndarray) -> np.ndarray:
        """Return the mask of strictly increasing stamps; count what it drops on ``topic``."""
        keep = keep_monotonic(t)
        self._drop(topic, 'stamp out of order or repeated', int(np.count_nonzero(~keep)))
        self._note_drops(topic, int(np.count_nonzero(keep)))
        return keep
