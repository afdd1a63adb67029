"""Error budget of the online odometry on long stretches: where its excess over the truth lies.

For each long-stretch drive of the online study (lab.studies.online), the online odometry's
excess over the true model, mean(ε_online) / mean(ε_true) - 1 (ε_t over 2 m increments of true
path), is split into the increments it is made of, so that the parts add up to the whole:

* **before**: increments that end before the change of ground (the calibration ground); the
  fixed file's ratio on the same increments says whether the file itself is already off there;
* **straddle**: increments that start before the change and end after it (driven partly on
  each ground: no causal odometry gets them right until the change is seen);
* **change**: increments that start after the change, less than ``--learn-m`` (10 m, the
  goal's "learned within") of true path after it: its detection and the first learning;
* **after**: the rest of the new ground (steady state): the parameter noise of the window, the
  forgetting, the reference noise.

Each part is printed as its share of the excess (points of the ratio), and the ratio online/true
on its own increments; ε_θ likewise. ``--set online.NAME=VALUE`` (repeatable) tries a setting.
Run::

    python -m lab.bench.online_budget --seeds 1 2 8 9
"""

from __future__ import annotations

import argparse
import sys

from lab.studies import online as study
import numpy as np

from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.core.online import online_odometer
from skidkin_ros.sim.simulate import SimConfig, simulate


def budget(seed: int, fixed: OdometryConfig, settings: dict, learn_m: float = 10.0,
           duration_s: float = 240.0) -> dict:
    """Return the split of one long-stretch drive's excess over the true model (see above)."""
    sim = simulate(SimConfig(duration_s=duration_s, seed=seed,
                             effects=study._effects('long stretches')))
    config = OdometryConfig.from_flat({**fixed.values, 'online.enabled': True, **settings})
    online = online_odometer(config).predict(
        sim.wheels, reference=study._reference(sim, np.random.default_rng(seed)))
    plain = Odometer.from_config(fixed).predict(sim.wheels)
    scores = {name: study._scores(sim, poses) for name, poses in
              (('fixed', plain.poses), ('online', online.poses),
               ('true', study._true_poses(sim, fixed['interval'])))}
    truth = sim.pose_at(sim.wheels.t_ns)
    path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(truth[:, :2], axis=0).T))])
    n = scores['online'][0].size
    start = np.arange(n)
    end = np.searchsorted(path, path[:n] + 2.0)
    switch = int(np.searchsorted(sim.wheels.t_ns, sim.start_ns + 0.5 * duration_s * 1e9))
    parts = {'before': end < switch, 'straddle': (start < switch) & (end >= switch),
             'change': (start >= switch) & (path[start] < path[switch] + learn_m),
             'after': path[start] >= path[switch] + learn_m}
    out = {'seed': seed}
    for which, col in (('t', 0), ('th', 1)):
        eps = {k: v[col] for k, v in scores.items()}
        total = eps['true'].sum()
        out[f'ratio_{which}'] = eps['online'].mean() / eps['true'].mean()
        for name, mask in parts.items():
            out[f'{name}_{which}'] = (eps['online'][mask] - eps['true'][mask]).sum() / total
            out[f'{name}_{which}_ratio'] = eps['online'][mask].mean() / eps['true'][mask].mean()
            out[f'{name}_{which}_fixed'] = eps['fixed'][mask].mean() / eps['true'][mask].mean()
    return out


def row(r: dict) -> str:
    """One drive as a markdown table row."""
    cells = [str(r['seed'])]
    for w in ('t', 'th'):
        cells.append(f"{r[f'ratio_{w}']:.2f}")
        cells += [f"+{r[f'{p}_{w}']:.2f} ({r[f'{p}_{w}_ratio']:.2f})"
                  for p in ('before', 'straddle', 'change', 'after')]
    cells.append(f"{r['before_t_fixed']:.2f} / {r['before_th_fixed']:.2f}")
    return '| ' + ' | '.join(cells) + ' |'


HEADER = ('| seed | online/true ε_t | before | straddle | change (10 m) | after | online/true ε_θ '
          '| before | straddle | change | after | fixed/true before (ε_t / ε_θ) |\n'
          + '|---' * 12 + '|')


def main(argv: list[str] | None = None) -> int:
    """Print the budget of every seed."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[1, 2])
    parser.add_argument('--learn-m', type=float, default=10.0)
    parser.add_argument('--set', action='append', default=[], metavar='online.NAME=VALUE')
    args = parser.parse_args(argv)
    settings = study.online_settings(parser, args.set)
    fixed = study.calibrated_file()
    print(HEADER)
    for seed in args.seeds:
        print(row(budget(seed, fixed, settings, args.learn_m)), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
