"""List the topics of a recording and choose the one to read (C7)."""

from __future__ import annotations

from typing import Sequence

from skidkin_ros.adapters.bags.common import TopicSummary
from skidkin_ros.errors import RecordingError


class TopicsMixin:
    """Topic listing, summary and selection."""

    def topics(self) -> dict[str, str]:
        """Return {topic: message type} of every topic in the recording."""
        result: dict[str, str] = {}
        for conn in self._connections():
            result.setdefault(conn.topic, conn.msgtype)
        return result

    def _count(self, topic: str) -> int:
        return sum(c.msgcount for c in self._connections() if c.topic == topic)

    def summary(self, time_ranges: bool = True) -> list[TopicSummary]:
        """Return every topic with type and count; with ``time_ranges``, first/last receive ns.

        Time ranges need one pass over the bag (streamed, messages not decoded).
        """
        first: dict[str, int] = {}
        last: dict[str, int] = {}
        if time_ranges:
            for conn, t_ns, _ in self._raw_stream(self._connections(), what='summary'):
                first.setdefault(conn.topic, t_ns)
                last[conn.topic] = t_ns
        return [TopicSummary(topic, msgtype, self._count(topic), first.get(topic),
                             last.get(topic))
                for topic, msgtype in sorted(self.topics().items())]

    def _listing(self) -> str:
        items = [f'{topic} [{msgtype}, {self._count(topic)} msgs]'
                 for topic, msgtype in sorted(self.topics().items())]
        return '; '.join(items) if items else 'none'

    def select(self, msgtypes: str | Sequence[str], topic: str | None = None,
               role: str = 'input') -> str:
        """Return the topic to read for ``role``: ``topic`` checked, or the only one of the types.

        Raise RecordingError (listing the topics there) when the named topic is absent, of
        another type or empty, or when no topic or several topics of the types exist.
        """
        wanted = (msgtypes,) if isinstance(msgtypes, str) else tuple(msgtypes)
        present = self.topics()
        kinds = ' or '.join(wanted)
        if topic is not None:
            if topic not in present:
                raise RecordingError(f'{role}: topic {topic} is not in {self.path}; expected a '
                                     f'{kinds} topic. Topics present: {self._listing()}')
            if present[topic] not in wanted:
                raise RecordingError(f'{role}: topic {topic} has type {present[topic]}, expected '
                                     f'{kinds}. Topics present: {self._listing()}')
            chosen = topic
        else:
            candidates = sorted(t for t, m in present.items() if m in wanted)
            if not candidates:
                raise RecordingError(f'{role}: no {kinds} topic in {self.path}. Topics present: '
                                     f'{self._listing()}. Record one, or name another source.')
            if len(candidates) > 1:
                raise RecordingError(f'{role}: several {kinds} topics ({", ".join(candidates)}); '
                                     f'name the one to use. Topics present: {self._listing()}')
            chosen = candidates[0]
            self.notes.append(f'{role}: using {chosen} [{present[chosen]}], the only '
                              f'{kinds} topic')
        if self._count(chosen) == 0:
            raise RecordingError(f'{role}: topic {chosen} has no messages in {self.path}. '
                                 f'Topics present: {self._listing()}')
        self._require_type(chosen, present[chosen])
        return chosen
