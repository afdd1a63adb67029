"""Run the online calibration study and print its table (lab.studies.online)."""

from __future__ import annotations

import sys
import time

from lab.studies.online import run_study, table


def main() -> int:
    tic = time.perf_counter()
    print(table(run_study()))
    print(f'\n({time.perf_counter() - tic:.0f} s)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
