"""The parameter uncertainty carried per wheel sample: cheap, and the same numbers as before.

A learner's parameter covariance is carried in its eigenbasis (T = S V) and read as p outer
products on floats; the file's fixed covariance keeps S in the parameters' coordinates. Both are
checked against the plain form: S' = F S + G d(increment)/dk with d(twist)/dk from
``twist_jacobian`` and S Sigma_k S^T by numpy.
"""

import numpy as np
import pytest
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry import sensitivity
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.noise import NoiseModel
from skidkin_ros.core.odometry.propagation import PoseCovariancePropagator
from skidkin_ros.core.odometry.uncertainty import ParameterUncertainty
from skidkin_ros.core.online import online_odometer
from skidkin_ros.sim.effects import make_effect
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate

GEOMETRY = Geometry(0.165, 0.555)
NOISE = NoiseModel(2e-4, 1e-4, 5e-4, 2e-3)
MODEL = get_model('edd_asymmetric')
K = np.array([DEFAULT_TRUE_PARAMS[spec.name] for spec in MODEL.params])


def _covariance(rng, size, condition, rank=None):
    """Return a random symmetric PSD covariance of given condition (rank < size: singular)."""
    basis, _ = np.linalg.qr(rng.normal(size=(size, size)))
    weights = 1e-4 * np.logspace(0.0, -np.log10(condition), size)
    if rank is not None:
        weights[rank:] = 0.0
    return (basis * weights) @ basis.T


def _steps(rng, count):
    """Plausible 1 kHz steps: (pose before, twist, dt) of a drive that turns both ways."""
    pose = np.zeros(3)
    for i in range(count):
        twist = (1.0 + 0.5 * np.sin(i / 700.0), 0.02 * rng.normal(),
                 0.6 * np.sin(i / 400.0) + 0.05 * rng.normal())
        dt = 1e-3 * (1.0 + 0.05 * rng.random())
        yield tuple(pose), twist, dt
        pose = pose + dt * np.array([twist[0] * np.cos(pose[2]), twist[0] * np.sin(pose[2]),
                                     twist[2]])


def _plain_step(sens, uncertainty, pose, twist, dt):
    jacobian = uncertainty.twist_jacobian(*twist)
    return sensitivity.propagate_sensitivity(sens, jacobian, pose[2], *twist, dt)


def _plain_read(sens, covariance):
    s = np.asarray(sens, dtype=float).T
    return s @ covariance @ s.T


def _relative(a, b):
    """Return max |a - b| over the scale of b (its largest entry, a variance)."""
    return float(np.abs(np.asarray(a) - np.asarray(b)).max() / max(np.abs(b).max(), 1e-300))


@pytest.mark.parametrize('seed,condition,rank', [(0, 1e2, None), (1, 1e6, None), (2, 1e3, 3)])
def test_learned_covariance_in_its_eigenbasis_gives_the_plain_numbers(seed, condition, rank):
    """Parameters set while driving (a learner's): the same S and published covariance."""
    rng = np.random.default_rng(seed)
    propagator = PoseCovariancePropagator(NOISE, [0.1] * 6, [0.1] * 6, None)
    propagator.reset(0.0)
    sens = None
    worst = 0.0
    for i, (pose, twist, dt) in enumerate(_steps(rng, 3000)):
        if i % 500 == 0:  # a new parameter vector and covariance: S is kept
            k = K * (1.0 + 0.02 * rng.normal(size=K.size))
            covariance = _covariance(rng, K.size, condition, rank)
            uncertainty = ParameterUncertainty.of_model(MODEL, k, GEOMETRY, covariance)
            propagator.set_parameters(uncertainty)
            sens = [(0.0, 0.0, 0.0)] * K.size if sens is None else sens
        propagator.step(pose, twist, dt)
        sens = _plain_step(sens, uncertainty, pose, twist, dt)
        expected = propagator.cov + _plain_read(sens, covariance)  # what was published
        worst = max(worst, _relative(propagator.total_cov(), expected))
        np.testing.assert_allclose(propagator.sensitivity, np.asarray(sens).T,
                                   rtol=0.0, atol=1e-12 * np.abs(sens).max())
    assert worst < 1e-12, worst
    assert propagator._basis is not None  # the learner's path was the one checked


def test_file_covariance_is_carried_as_before_bit_for_bit():
    """The file's fixed covariance: S and the published covariance exactly the plain ones."""
    rng = np.random.default_rng(5)
    covariance = _covariance(rng, K.size, 1e3)
    uncertainty = ParameterUncertainty.of_model(MODEL, K, GEOMETRY, covariance)
    propagator = PoseCovariancePropagator(NOISE, [0.1] * 6, [0.1] * 6, uncertainty)
    plain = PoseCovariancePropagator(NOISE, [0.1] * 6, [0.1] * 6, None)
    propagator.reset(0.0)
    plain.reset(0.0)
    sens = [(0.0, 0.0, 0.0)] * K.size
    for pose, twist, dt in _steps(rng, 1500):
        propagator.step(pose, twist, dt)
        plain.step(pose, twist, dt)
        sens = _plain_step(sens, uncertainty, pose, twist, dt)
        assert propagator._sens == sens
        c = _plain_read(sens, uncertainty.covariance)
        expected = tuple(a + float(b) for a, b in zip(plain.total_upper(), (
            c[0, 0], c[0, 1], c[0, 2], c[1, 1], c[1, 2], c[2, 2])))
        assert propagator.total_upper() == expected
    assert propagator._basis is None


def test_a_new_covariance_of_another_size_restarts_the_sensitivity():
    rng = np.random.default_rng(7)
    propagator = PoseCovariancePropagator(NOISE, [0.1] * 6, [0.1] * 6, None)
    propagator.reset(0.0)
    propagator.set_parameters(ParameterUncertainty.of_model(
        MODEL, K, GEOMETRY, _covariance(rng, K.size, 10.0)))
    for pose, twist, dt in _steps(rng, 200):
        propagator.step(pose, twist, dt)
    assert np.abs(propagator.sensitivity).max() > 0.0
    small = get_model('edd_symmetric')
    k = np.array([0.9, 1.1])[:len(small.params)]
    propagator.set_parameters(ParameterUncertainty.of_model(small, k, GEOMETRY,
                                                            np.diag([1e-4] * k.size)))
    assert propagator.sensitivity.shape == (3, k.size)
    assert not np.any(propagator.sensitivity)
    propagator.set_parameters(None)
    assert propagator.total_upper() == propagator._upper


def test_online_odometer_publishes_the_plain_numbers(monkeypatch):
    """A learning odometer publishes the plain numbers over a drive with a ground change.

    Poses bit for bit, covariances to 1e-12 of their size, against the same odometer with S
    carried in the parameters' coordinates and read by numpy (the arithmetic before).
    """
    effect = make_effect('terrain_regime', 0.25, mode='time', switch_frac=0.5, yaw=0.15)
    sim = simulate(SimConfig(duration_s=25.0, seed=11, wheel_rate_hz=1000.0,
                             effects=(effect,)))
    reference = sim.truth_at(np.arange(sim.start_ns, sim.end_ns, 100_000_000))
    flat = {'model': 'edd_asymmetric',
            **{f'models.edd_asymmetric.{k}': v for k, v in DEFAULT_TRUE_PARAMS.items()},
            'models.edd_asymmetric.noise.calibrated': True,
            'models.edd_asymmetric.noise.var_x_per_m': 1.2e-4,
            'models.edd_asymmetric.noise.var_yaw_per_rad': 2e-4, 'online.enabled': True}
    config = OdometryConfig.from_flat(flat)

    def run():
        odometer = online_odometer(config)
        odometer.reset()
        rows = list(zip(reference.t_ns.tolist(), reference.x.tolist(), reference.y.tolist(),
                        reference.yaw.tolist()))
        j, poses, covs = 0, [], []
        for t, left, right in zip(sim.wheels.t_ns.tolist(), sim.wheels.omega_l.tolist(),
                                  sim.wheels.omega_r.tolist()):
            while j < len(rows) and rows[j][0] <= t:
                odometer.reference_sample(*rows[j])
                j += 1
            estimate = odometer.update(t, left, right)
            if estimate is not None:
                poses.append(estimate.pose)
                covs.append(estimate.pose_covariance)
        assert odometer.counters['online_segments'] > 0
        planar = np.asarray(covs)[:, [0, 1, 5, 6, 7, 11, 30, 31, 35]]
        return np.asarray(poses), planar, odometer.covariance._basis is not None

    poses, covs, eigen = run()
    use = PoseCovariancePropagator._use
    monkeypatch.setattr(PoseCovariancePropagator, '_use',
                        lambda self, parameters, eigen: use(self, parameters, False))
    plain_poses, plain_covs, plain_eigen = run()
    assert eigen and not plain_eigen
    assert np.array_equal(poses, plain_poses)
    scale = np.abs(plain_covs).max(axis=1)
    assert float((np.abs(covs - plain_covs).max(axis=1) / scale).max()) < 1e-12
