"""Where the online odometry's error lies on long stretches, and what online.* settings change.

For each seed, the long-stretch drive of the online study (lab.studies.online): ε_t of
the online odometry over the true model's, on the whole drive, on each half (the calibration
ground, then the new one) and in twelfths of the drive (the change is at the start of the
seventh), with the learning counts and the learned parameters against the new ground's.
``--set online.NAME=VALUE`` (repeatable) overrides a setting of the online calibrator. Run::

    python -m lab.bench.online_profile --seeds 1 2 8 9
    python -m lab.bench.online_profile --seeds 1 2 8 9 --set online.prior_sigma=0.2
"""

from __future__ import annotations

import argparse
import sys

from lab.studies import online as study
import numpy as np

from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.online import online_odometer
from skidkin_ros.sim.simulate import SimConfig, simulate


def _new_ground() -> dict[str, float]:
    return study.true_grounds()[1]


def profile(seed: int, fixed: OdometryConfig, settings: dict[str, float]) -> str:
    """Return one seed's profile as text."""
    sim = simulate(SimConfig(duration_s=240.0, seed=seed,
                             effects=study._effects('long stretches')))
    config = OdometryConfig.from_flat({**fixed.values, 'online.enabled': True, **settings})
    odometer = online_odometer(config)
    online = odometer.predict(sim.wheels,
                              reference=study._reference(sim, np.random.default_rng(seed)))
    eps_online = study._scores(sim, online.poses)[0]
    eps_true = study._scores(sim, study._true_poses(sim, fixed['interval']))[0]
    half = len(eps_online) // 2

    def ratio(part: slice | np.ndarray) -> float:
        return float(eps_online[part].mean() / eps_true[part].mean())
    twelfths = ' '.join(f'{ratio(part):.2f}'
                        for part in np.array_split(np.arange(len(eps_online)), 12))
    counts = {k: v for k, v in odometer.counters.items() if k.startswith('online_')}
    truth = _new_ground()
    off = ' '.join(f'{name} {100 * (value / truth[name] - 1):+.1f} %'
                   for name, value in odometer.learner.values.items())
    return (f'seed {seed}: online/true eps_t {ratio(slice(None)):.2f} (first half '
            f'{ratio(slice(None, half)):.2f}, second half {ratio(slice(half, None)):.2f})\n'
            f'  twelfths: {twelfths}\n  {counts}\n  learned vs the new ground: {off}')


def main(argv: list[str] | None = None) -> int:
    """Print the profile of every seed."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[1, 2])
    parser.add_argument('--set', action='append', default=[], metavar='online.NAME=VALUE')
    args = parser.parse_args(argv)
    settings = study.online_settings(parser, args.set)
    fixed = study.calibrated_file()
    for seed in args.seeds:
        print(profile(seed, fixed, settings), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
