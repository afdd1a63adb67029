"""Run the augmented online calibration study; print its table (lab.studies.online_augmented)."""

from __future__ import annotations

import argparse
import sys
import time

from lab.studies.online_augmented import run_seed, table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--seeds', type=int, nargs='+', default=[1, 2, 11, 12, 13, 14])
    parser.add_argument('--seconds', type=float, default=200.0, help='drive duration (s)')
    parser.add_argument('--effect', default='speed_slip',
                        choices=('speed_slip', 'ratio_yaw_slip', 'residual_model',
                                 'residual_rate'))
    args = parser.parse_args(argv)
    tic = time.process_time()
    print(table([run_seed(seed, args.seconds, args.effect) for seed in args.seeds]))
    print(f'\n({time.process_time() - tic:.0f} s CPU)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
