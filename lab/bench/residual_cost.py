"""Per-wheel-sample cost of the residual model in Odometer.predict (CPU, min of 3 runs).

    PYTHONPATH=.:test python lab/bench/residual_cost.py

Rows: the plain edd_symmetric model, the residual model (every coefficient non-zero), the
same with the covariance of every coefficient carried into the pose covariance, a level-3 file
(its terms only) and a level-6 file with the covariance of its terms.
"""

import pathlib
import tempfile
import time

import numpy as np
from skidkin_ros.core.kinematics import residual
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.odometer import Odometer
from skidkin_ros.sim.simulate import SimConfig, simulate
import test_residual_model as files


def main() -> None:
    wheels = simulate(SimConfig(duration_s=60.0, seed=4)).wheels
    tmp = pathlib.Path(tempfile.mkdtemp())
    names = residual.coefficient_names()
    rng = np.random.default_rng(1)
    values = {name: float(rng.normal(0.0, 0.01)) for name in names}
    values.update(files.RANGES)
    configs = {}
    # a file of level 3 (its terms only) and one of level 6 with their covariance: what a fit
    # below the top level writes; terms whose coefficients are all 0 are not evaluated
    level3 = {**values, **{name: 0.0 for name in names
                           if name.split('_', 1)[1] not in residual.term_names(3)}}
    level6 = [name for name in names if name.split('_', 1)[1] in residual.term_names(6)]
    level6_values = {**values, **{name: 0.0 for name in names if name not in level6}}
    for label, vals, cov in (
            ('residual', values, [0.0] * len(names) ** 2),
            ('residual + covariance', values, files._covariance(list(names), 1e-4)),
            ('level 3', level3, [0.0] * len(names) ** 2),
            ('level 6 + covariance', level6_values, files._covariance(level6, 1e-4))):
        (tmp / label).mkdir()
        configs[label] = OdometryConfig.from_file(files._calibrated_file(tmp / label, vals, cov))
    configs = {'plain edd_symmetric': OdometryConfig.from_flat({
        'wheel_radius': 0.1651, 'track_width': 0.555, 'robot': 'sim_husky',
        'model': 'edd_symmetric', 'interval': 'ending', 'models.edd_symmetric.alpha': 0.9,
        'models.edd_symmetric.b_hat': 0.85, 'models.edd_symmetric.noise.calibrated': True}),
        **configs}
    times: dict[str, list[float]] = {}
    for _ in range(3):
        for label, config in configs.items():
            odometer = Odometer.from_config(config)
            start = time.process_time()
            odometer.predict(wheels)
            times.setdefault(label, []).append(
                (time.process_time() - start) / len(wheels.t_ns) * 1e6)
    for label, values_us in times.items():
        print(f'{label:24s} {min(values_us):7.1f} us per wheel sample')


if __name__ == '__main__':
    main()
