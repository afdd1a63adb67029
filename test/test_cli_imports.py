"""The `skidkin` command starts without the libraries only some commands need."""

import subprocess
import sys


def test_the_cli_imports_neither_matplotlib_nor_scipy_signal():
    # matplotlib (the reports) and scipy.signal (the simulator's filters) cost about 1 s of CPU
    # each to import; every command (groundtruth too) used to pay for them at start-up.
    code = ('import sys, skidkin_ros.cli.main; '
            "print(sorted(m for m in ('matplotlib', 'scipy.signal') if m in sys.modules))")
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=120, check=True)
    assert done.stdout.split() == ['[]']
    code = 'import sys, skidkin_ros.report.page; print("matplotlib" in sys.modules)'
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=120, check=True)
    assert done.stdout.split() == ['True']   # the probe sees a module that is imported
