"""Per-wheel-sample cost of the residual model in Odometer.predict (CPU, min of 3 runs).

    PYTHONPATH=.:test python lab/bench/residual_cost.py

Rows: the plain edd_symmetric model, the residual model (every coefficient non-zero), and the
same with the covariance of every coefficient carried into the pose covariance.
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
    for label, cov in (('residual', [0.0] * len(names) ** 2),
                       ('residual + covariance', files._covariance(list(names), 1e-4))):
        (tmp / label).mkdir()
        configs[label] = OdometryConfig.from_file(files._calibrated_file(tmp / label, values, cov))
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
