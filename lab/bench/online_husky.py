"""Online calibration on the real Husky windows, beside the files users run instead.

The study: lab.studies.online_husky.

Streams the 603 windows of data/husky/drive_husky_windows.csv in time order through the node's
odometer, the lidar-ICP poses (held repeats dropped, about 10 Hz) as the reference, and prints
ε_t / ε_θ on the odd-calib_step windows for: ideal differential drive (published geometry, and
with Clearpath's wheel_separation_multiplier 1.875), the calibrator's plain least-squares and
calibrated files, online learning from the ideal and from the calibrated file (with the
reference on every window, on the training windows only, and only on the first half), and the
gyro fused. About six minutes on one core. ``--windows N``: the first N windows only.
"""

from __future__ import annotations

import argparse
import sys
import time

from lab.studies.online import online_settings
from lab.studies.online_husky import HORIZON, run_study, tables


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--windows', type=int, default=None, help='the first N windows only')
    parser.add_argument('--horizon', type=float, nargs=2, default=HORIZON,
                        metavar=('M', 'RAD'), help='online.horizon and online.horizon_rad '
                        f'(default {HORIZON[0]:g} m {HORIZON[1]:g} rad)')
    parser.add_argument('--no-gyro', action='store_true', help='leave out the gyro rows')
    parser.add_argument('--set', action='append', default=[], metavar='online.NAME=VALUE',
                        help='an online.* setting for every online row')
    args = parser.parse_args(argv)
    tic = time.process_time()
    study = run_study(args.windows, tuple(args.horizon), online_settings(parser, args.set),
                      gyro=not args.no_gyro)
    print(tables(study))
    print(f'\n({time.process_time() - tic:.0f} s of CPU)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
