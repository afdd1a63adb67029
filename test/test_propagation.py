"""Covariance propagation: first-order propagation matches Monte Carlo of the same noise."""

import numpy as np
import pytest
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.integrator import body_increment, compose, rollout
from skidkin_ros.core.odometry.noise import NoiseModel
from skidkin_ros.core.odometry.propagation import PoseCovariancePropagator, predict, to_6x6

GEOM = Geometry(0.3, 1.2)
NOISE = NoiseModel(var_x_per_m=4e-4, var_y_per_m=2e-4, var_yaw_per_m=1e-4, var_yaw_per_rad=2e-3)


def _drive(n=200):
    t_ns = np.arange(n, dtype=np.int64) * 50_000_000
    wl = np.where(np.arange(n) < n // 2, 3.0, 1.0)
    wr = np.where(np.arange(n) < n // 2, 3.0, 4.0)
    return t_ns, wl, wr


def test_mean_is_the_integrator_pose():
    t_ns, wl, wr = _drive()
    model = get_model('edd_symmetric').bind({'alpha': 0.9, 'b_hat': 1.5}, GEOM)
    pose, _ = predict([0, 0, 0], np.zeros((3, 3)), t_ns, wl, wr, model, NOISE)
    # the default interval, ending: sample k's speeds over [t_k-1, t_k]
    expected = rollout(model.twist(wl[1:], wr[1:]), np.diff(t_ns) * 1e-9)[-1]
    np.testing.assert_allclose(pose, expected, atol=1e-12)


def test_propagated_covariance_matches_monte_carlo():
    t_ns, wl, wr = _drive(120)
    model = get_model('ideal_dd').bind({}, GEOM)
    _, cov = predict([0, 0, 0], np.zeros((3, 3)), t_ns, wl, wr, model, NOISE)
    rng = np.random.default_rng(7)
    samples = 4000
    x = np.zeros(samples)
    y = np.zeros(samples)
    th = np.zeros(samples)
    for i in range(len(t_ns) - 1):
        dt = (t_ns[i + 1] - t_ns[i]) * 1e-9
        dx, dy, dth = body_increment(*model.twist(wl[i + 1], wr[i + 1]), dt)
        step = NOISE.step_covariance(np.hypot(dx, dy), dth)
        noise = rng.normal(size=(samples, 3)) * np.sqrt(np.diag(step))
        x, y, th = compose(x, y, th, dx + noise[:, 0], dy + noise[:, 1], dth + noise[:, 2])
    empirical = np.cov(np.stack([x, y, th]))
    np.testing.assert_allclose(np.diag(cov), np.diag(empirical), rtol=0.12)
    assert abs(cov[0, 1] - empirical[0, 1]) < 0.12 * np.sqrt(cov[0, 0] * cov[1, 1])


def test_streaming_propagator_grows_with_motion_and_falls_back_without_calibration():
    model = get_model('ideal_dd').bind({}, GEOM)
    prop = PoseCovariancePropagator(NOISE, [1] * 6, [2] * 6)
    pose = np.zeros(3)
    before = prop.pose_covariance_6x6().copy()
    for _ in range(10):
        twist = model.twist(2.0, 3.0)
        prop.step(pose, twist, 0.05)
    after = prop.pose_covariance_6x6()
    assert np.all(np.diag(after)[[0, 1, 5]] > np.diag(before)[[0, 1, 5]])
    assert np.all(np.linalg.eigvalsh(after) > 0)
    still = prop.twist_covariance_6x6(np.zeros(3), 0.05)
    assert np.all(np.diag(still) > 0)
    fixed = PoseCovariancePropagator(None, [1, 2, 3, 4, 5, 6], [6, 5, 4, 3, 2, 1])
    fixed.step(pose, model.twist(2.0, 3.0), 0.05)
    np.testing.assert_array_equal(np.diag(fixed.pose_covariance_6x6()), [1, 2, 3, 4, 5, 6])
    np.testing.assert_array_equal(np.diag(fixed.twist_covariance_6x6(np.ones(3), 0.05)),
                                  [6, 5, 4, 3, 2, 1])


def test_to_6x6_places_yaw_in_the_last_row_and_column():
    cov3 = np.array([[1.0, 0.1, 0.2], [0.1, 2.0, 0.3], [0.2, 0.3, 3.0]])
    full = to_6x6(cov3)
    assert full[5, 5] == 3.0 and full[0, 5] == 0.2 and full[1, 5] == 0.3 and full[2, 2] > 1e3


def test_plain_math_step_equals_the_matrix_form():
    """propagate_step writes F P F^T + G Q G^T out by hand; check it against numpy's products."""
    from skidkin_ros.core.odometry.propagation import propagate_step, step_jacobians
    rng = np.random.default_rng(3)
    for _ in range(50):
        pose = rng.normal(size=3) * [5.0, 5.0, 3.0]
        root = rng.normal(size=(3, 3))
        cov = root @ root.T
        twist = rng.normal(size=3)
        dt = float(rng.uniform(0.001, 0.2))
        jac_in = rng.normal(size=(3, 2))
        new_pose, new_cov = propagate_step(pose, cov, twist, dt, NOISE, jac_in, 0.3)
        dx, dy, dth = body_increment(*twist, dt)
        np.testing.assert_allclose(new_pose, compose(*pose, dx, dy, dth), atol=1e-12)
        jac_pose, jac_incr = step_jacobians(pose[2], dx, dy)
        q_body = NOISE.step_covariance(np.hypot(dx, dy), dth) + 0.3 * jac_in @ jac_in.T
        expected = jac_pose @ cov @ jac_pose.T + jac_incr @ q_body @ jac_incr.T
        np.testing.assert_allclose(new_cov, expected, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(new_cov, new_cov.T)


def test_predict_runs_a_stateful_model_as_the_node_does():
    """An augmented model with a lag: predict() gives the node's pose and covariance."""
    from skidkin_ros.core.kinematics.augmented import AugmentedModel
    from skidkin_ros.core.odometry.integrator import (rollout_stream, SampleStatus,
                                                      StreamingIntegrator)
    base = get_model('edd_symmetric').bind({'alpha': 0.9, 'b_hat': 1.5}, GEOM)
    source = AugmentedModel('edd_symmetric', ('first_order_lag', 'lateral_skid')).bind(
        base, {'first_order_lag': {'tau_s': 0.3}, 'lateral_skid': {'k': 0.05}})
    t_ns, wl, wr = _drive()
    start = [1.0, -2.0, 0.3]
    pose, cov = predict(start, np.zeros((3, 3)), t_ns, wl, wr, source, NOISE)
    np.testing.assert_allclose(pose, rollout_stream(source, t_ns, wl, wr, start)[-1],
                               atol=1e-12)
    # the memoryless twist (what predict used before) is far from it: the lag matters here
    assert np.abs(pose - rollout(base.twist(wl[:-1], wr[:-1]), np.diff(t_ns) * 1e-9,
                                 start)[-1]).max() > 0.05
    # the node's path: the streaming integrator's steps into the streaming propagator
    integrator = StreamingIntegrator(source)
    integrator.reset(start)
    prop = PoseCovariancePropagator(NOISE, [1] * 6, [2] * 6)
    prop.cov = np.zeros((3, 3))  # the node starts from a tiny variance; predict() from cov
    for t, left, right in zip(t_ns.tolist(), wl.tolist(), wr.tolist()):
        result = integrator.step(t, left, right)
        if result.status is SampleStatus.INTEGRATED:
            prop.step(result.start_pose, result.step_twist, result.dt_s)
    np.testing.assert_allclose(cov, prop.cov, rtol=1e-12, atol=1e-15)


def test_time_in_motion_grows_the_covariance_only_while_the_wheels_turn():
    """The per-second part adds rate * dt per moving step, nothing at an exact standstill."""
    timed = NoiseModel(0.0, 0.0, 0.0, 0.0, var_x_per_s=2e-4, var_yaw_per_s=5e-4)
    model = get_model('ideal_dd').bind({}, GEOM)
    n = 41
    t_ns = np.arange(n, dtype=np.int64) * 50_000_000
    still = np.zeros(n)
    _, parked = predict([0, 0, 0], np.zeros((3, 3)), t_ns, still, still, model, timed)
    np.testing.assert_array_equal(parked, np.zeros((3, 3)))
    # turning on the spot for 2 s: no distance, no per-radian rate; the time part alone
    spin = np.full(n, 2.0)
    _, turned = predict([0, 0, 0], np.zeros((3, 3)), t_ns, -spin, spin, model, timed)
    assert turned[2, 2] == pytest.approx(5e-4 * 2.0, rel=1e-9)
    assert turned[0, 0] + turned[1, 1] == pytest.approx(2e-4 * 2.0, rel=1e-9)
    # the published twist variance carries it per sample, and not at a standstill
    prop = PoseCovariancePropagator(timed, [1] * 6, [2] * 6)
    moving = prop.twist_covariance_6x6((0.0, 0.0, 1.0), 0.05)
    resting = prop.twist_covariance_6x6((0.0, 0.0, 0.0), 0.05)
    assert moving[5, 5] == pytest.approx(5e-4 / 0.05)
    assert resting[5, 5] < 1e-3 * moving[5, 5]
