"""Progress that reaches a log: a line per 10 % with the count, the rate and the time left."""

from __future__ import annotations

import io
import re

from skidkin_ros.cli.progress import Progress


class _Tty(io.StringIO):

    def isatty(self) -> bool:
        return True


def test_a_log_gets_one_line_per_tenth_with_rate_and_time_left():
    stream = io.StringIO()  # not a terminal, as under nohup, CI or a pipe
    progress = Progress('kiss-icp', 'frames', stream=stream)
    for done in range(0, 1001, 7):
        progress(done, 1000)
    progress(1000, 1000)
    lines = stream.getvalue().splitlines()
    assert len(lines) == 10
    shares = [int(re.match(r'kiss-icp: (\d+) %', line).group(1)) for line in lines]
    assert all(10 * (i + 1) <= share <= 10 * (i + 1) + 1 for i, share in enumerate(shares))
    assert re.fullmatch(r'kiss-icp: 10 % \(105/1000 frames\), [\d.]+ frames/s, (about [\d.]+ '
                        r'(s|min|h) left|time left unknown)', lines[0])
    assert lines[-1].endswith('done')


def test_jumps_print_one_line_and_a_terminal_gets_a_bar():
    stream = io.StringIO()
    progress = Progress('chunks', 'frames', stream=stream)
    progress(350, 1000)  # three chunks read from the cache at once
    progress(360, 1000)
    assert len(stream.getvalue().splitlines()) == 1
    tty = _Tty()
    bar = Progress('kiss-icp', 'frames', stream=tty)
    bar(5, 10)
    bar(10, 10)
    bar.close()
    assert 'kiss-icp' in tty.getvalue() and '10/10' in tty.getvalue()
    assert ' % (' not in tty.getvalue()  # the bar, not log lines
