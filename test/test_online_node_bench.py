"""The online node benchmark runs end to end at smoke size: two real nodes, one learning."""

from __future__ import annotations

from pathlib import Path
import re
import subprocess
import sys

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.ros
def test_online_node_bench_measures_both_nodes_and_the_online_one_learns():
    proc = subprocess.run([sys.executable, '-m', 'lab.bench.online_node_bench', '--seconds', '8',
                           '--rounds', '2', '--rate', '200'], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout
    cpu = {label: float(value) for label, value in
           re.findall(r'online (off|on): ([0-9.]+) us CPU per wheel sample sent', out)}
    assert set(cpu) == {'off', 'on'} and all(v > 0 for v in cpu.values()), out
    assert re.search(r'ratio on / off per wheel sample sent: [0-9.]+', out), out
    # the online node took the reference and learned from it (the reference is 10 % slower)
    learned = re.search(r'node on /diagnostics: .*online.state (\w+), count.online_segments '
                        r'(\d+), count.reference_accepted (\d+), online.alpha_l ([0-9.]+)', out)
    assert learned, out
    assert int(learned.group(3)) > 40
    assert int(learned.group(2)) >= 1 and float(learned.group(4)) < 0.88
