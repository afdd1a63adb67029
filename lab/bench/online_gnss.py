"""Run the GNSS-without-heading study (lab.studies.online_gnss) and print its table.

Seeds: long stretches 1 and effect-free 5 were looked at while the position-only learner was
built (its HORIZON_FACTOR and INFORMATION_FACTOR); the others are held out.
"""

from __future__ import annotations

import argparse
import sys
import time

from lab.studies.online import calibrated_file
from lab.studies.online_gnss import COLUMNS, run_drive

TUNED = {'long stretches': (1,), 'effect-free': (5,)}
HELD_OUT = {'long stretches': (2, 8, 9), 'effect-free': (6, 7, 14)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seconds', type=float, default=240.0, help='drive length (s)')
    parser.add_argument('--quick', action='store_true', help='the tuned seeds only')
    args = parser.parse_args(argv)
    tic = time.perf_counter()
    fixed = calibrated_file()
    print('| case | seed | path m | ' + ' | '.join(f'eps_t {c}' for c in COLUMNS)
          + ' | eps_th fixed / true / full / positions 5 Hz | positions 5 Hz / fixed |')
    print('|' + '---|' * (len(COLUMNS) + 5))
    for case in ('long stretches', 'effect-free'):
        seeds = TUNED[case] + (() if args.quick else HELD_OUT[case])
        for seed in seeds:
            r = run_drive(case, seed, fixed, args.seconds)
            tag = f'{seed}' + (' (tuned)' if seed in TUNED[case] else '')
            pos = r['positions 5 Hz']
            print(f'| {case} | {tag} | {r["path_m"]:.0f} | '
                  + ' | '.join(f'{r[c][0]:.4f}' for c in COLUMNS)
                  + f' | {r["fixed"][1]:.4f} / {r["true"][1]:.4f} / {r["full"][1]:.4f} / '
                  f'{pos[1]:.4f} | {pos[0] / r["fixed"][0]:.2f} |', flush=True)
    print(f'\n({time.perf_counter() - tic:.0f} s)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
