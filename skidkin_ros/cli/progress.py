"""Progress of a long step, for a person at a terminal and for a log.

On a terminal (stderr is a tty) a tqdm bar; otherwise one line per tenth of the work, each
with the work done, the rate and the estimated time left, so a run started by a script, CI or
``nohup`` says in its log how far it got::

    kiss-icp: 30 % (912/3040 frames), 41.3 frames/s, about 51 s left

The library code takes a plain ``on_progress(done, total)`` callback; only the CLI builds a
:class:`Progress` and hands it over.
"""

from __future__ import annotations

import sys
import time
from typing import IO

__all__ = ['Progress']


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f'{seconds:.0f} s'
    if seconds < 5400:
        return f'{seconds / 60:.1f} min'
    return f'{seconds / 3600:.1f} h'


class Progress:
    """Report ``(done, total)`` of one step as a bar (terminal) or as log lines (every 10 %).

    ``desc`` names the step, ``unit`` what is counted (plural). ``lines`` forces log lines
    (True) or a bar (False); by default a bar only when ``stream`` is a terminal.
    """

    def __init__(self, desc: str, unit: str, stream: IO[str] | None = None,
                 lines: bool | None = None, step: float = 0.1) -> None:
        self.desc = desc
        self.unit = unit
        self.stream = stream if stream is not None else sys.stderr
        tty = bool(getattr(self.stream, 'isatty', lambda: False)())
        self.lines = (not tty) if lines is None else lines
        self.step = step
        self._bar = None
        self._next = step
        self._start = time.monotonic()

    def __call__(self, done: int, total: int) -> None:
        """Record that ``done`` of ``total`` are done (both counts from the start)."""
        total = max(int(total), 1)
        done = min(max(int(done), 0), total)
        if not self.lines:
            self._update_bar(done, total)
            return
        fraction = done / total
        if fraction + 1e-12 >= self._next:
            self._line(done, total)
            self._next = (int(fraction / self.step + 1e-9) + 1) * self.step

    def _update_bar(self, done: int, total: int) -> None:
        if self._bar is None:
            from tqdm import tqdm
            self._bar = tqdm(total=total, desc=self.desc, unit=self.unit.rstrip('s') or 'it',
                             file=self.stream)
        if self._bar.total != total:
            self._bar.total = total
        self._bar.update(done - self._bar.n)

    def _line(self, done: int, total: int) -> None:
        elapsed = time.monotonic() - self._start
        rate = done / elapsed if elapsed > 0 else 0.0
        left = (total - done) / rate if rate > 0 else float('inf')
        tail = 'done' if done >= total else (f'about {_duration(left)} left' if rate > 0
                                             else 'time left unknown')
        print(f'{self.desc}: {100.0 * done / total:.0f} % ({done}/{total} {self.unit}), '
              f'{rate:.1f} {self.unit}/s, {tail}', file=self.stream, flush=True)

    def close(self) -> None:
        """End the bar, if any."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
