"""Online calibration while the reference is missing: which ground the odometry runs."""

import collections
import dataclasses

import numpy as np
import pytest
from skidkin_ros.core.drive import ImuSamples
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.online import dwell, online_odometer
from skidkin_ros.core.online.grounds import Ground
from skidkin_ros.core.online.gyrochoice import GyroChoice
from skidkin_ros.core.online.holding import HoldingBlend
from skidkin_ros.sim.effects import make_effect
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate

FILE = {'model': 'edd_asymmetric',
        **{f'models.edd_asymmetric.{k}': v for k, v in DEFAULT_TRUE_PARAMS.items()},
        'models.edd_asymmetric.noise.calibrated': True, 'online.enabled': True}
CUT_S = (120.0, 140.0)
GYRO_BIAS = 0.003   # rad/s, on top of the simulator's white noise


def _drive(mode, seed=3):
    if mode == 'alternate':
        effect = make_effect('terrain_regime', 0.25, mode='alternate', period_m=4.0, yaw=0.15)
    else:
        effect = make_effect('terrain_regime', 0.25, mode='time', switch_frac=0.4, yaw=0.15)
    return simulate(SimConfig(duration_s=160.0, seed=seed, effects=(effect,)))


def _reference(sim, cut=CUT_S):
    t = np.arange(sim.start_ns, sim.end_ns, 100_000_000)
    if cut is not None:
        rel = (t - sim.start_ns) * 1e-9
        t = t[(rel < cut[0]) | (rel >= cut[1])]
    return sim.truth_at(t)


def _gyro(sim, stop_s=None):
    """Return the simulator's gyro with a 0.003 rad/s bias; ``stop_s``: none from then on."""
    imu = dataclasses.replace(sim.imu, yaw_rate=sim.imu.yaw_rate + GYRO_BIAS)
    if stop_s is not None:
        keep = (imu.t_ns - sim.start_ns) * 1e-9 < stop_s
        imu = ImuSamples(imu.t_ns[keep], imu.yaw_rate[keep])
    return imu


def _run(sim, reference, record=False, imu=None):
    """Predict with online calibration; with record, what is in force after every step.

    ``imu``: the odometry fuses this gyro (imu.mode fuse).
    """
    flat = FILE if imu is None else {**FILE, 'imu.mode': 'fuse'}
    odometer = online_odometer(OdometryConfig.from_flat(flat))
    learner, seen = odometer.learner, []
    if record:
        step = learner.wheel_step

        def wheel_step(t1_ns, wheels, twist):
            changed = step(t1_ns, wheels, twist)
            k, cov = learner.in_force()
            seen.append(((t1_ns - sim.start_ns) * 1e-9, learner.state(t1_ns),
                         learner.hold_weight(), k.copy(), learner.active.k.copy(),
                         learner._blend, learner.summary(),
                         np.stack([g.k for g in learner.grounds]), learner.covariance))
            return changed
        learner.wheel_step = wheel_step
    return odometer, odometer.predict(sim.wheels, imu=imu, reference=reference), seen


@pytest.fixture(scope='module')
def alternating():
    return _drive('alternate')


def test_alternating_grounds_are_blended_while_holding_and_not_after(alternating, monkeypatch):
    """The Markov chain's blend (the dwell model left out: its own tests are below)."""
    monkeypatch.setattr(HoldingBlend, '_dwell_plan', lambda self, grounds: None)
    odometer, prediction, seen = _run(alternating, _reference(alternating), record=True)
    assert odometer.counters['online_hold_blend'] == 1
    assert odometer.counters['online_switch'] >= 3   # the grounds alternated before the cut
    holding = [s for s in seen if CUT_S[0] + 1.5 < s[0] < CUT_S[1] and s[1] == 'holding']
    assert len(holding) > 300
    weights = np.array([s[2] for s in holding])
    # the active ground first, then toward the grounds' recent shares (about half each here)
    assert weights[0] > 0.8 and 0.3 < weights[-1] < 0.7
    assert np.all(np.diff(weights) <= 1e-12)
    names = odometer.learner.model.param_names
    for t, state, weight, k, active_k, blend, summary, ks, active_cov in holding[::50]:
        # what the odometry integrates is a weighted mean of the grounds' parameters ...
        assert blend is not None and blend[0][0] == weight
        assert np.all(k >= ks.min(axis=0) - 1e-12) and np.all(k <= ks.max(axis=0) + 1e-12)
        assert not np.array_equal(k, active_k)
        # ... with the spread between them as uncertainty, wider than the active ground's
        assert np.all(np.diag(blend[2]) > np.diag(active_cov))
        # /diagnostics (and ~/save_calibration) keep the active ground's own values
        assert [summary[name] for name in names] == active_k.tolist()
        assert summary['hold_weight'] == weight
    after = [s for s in seen if s[0] > CUT_S[1] + 0.5]
    assert after and all(s[2] == 1.0 and s[5] is None for s in after)
    assert all(np.array_equal(s[3], s[4]) for s in after)
    assert np.all(np.isfinite(prediction.poses))


def test_the_blend_errs_less_than_holding_the_active_ground(alternating, monkeypatch):
    """Gain less error over the dropout with the blend than holding the active ground.

    On this drive the robot crosses from the active ground onto the other one during the
    dropout, as it did before it (the case the blend is for).
    """
    reference = _reference(alternating)
    truth = alternating.truth.poses
    t = (alternating.wheels.t_ns - alternating.start_ns) * 1e-9
    i0, i1 = np.searchsorted(t, CUT_S[0]), np.searchsorted(t, CUT_S[1])

    def drift(poses):   # the pose error gained over the dropout, in the start's frame
        return float(np.hypot(*((poses[i1] - poses[i0]) - (truth[i1] - truth[i0]))[:2]))
    blended = drift(_run(alternating, reference)[1].poses)
    monkeypatch.setattr(HoldingBlend, '_hold_plan_now', lambda self: None)
    held = drift(_run(alternating, reference)[1].poses)
    assert blended < held


@pytest.mark.parametrize('mode, cut', [('time', CUT_S), ('alternate', None)])
def test_no_blend_after_one_change_nor_while_the_reference_comes(mode, cut, monkeypatch):
    """Hold the active ground after one change; never blend while the reference comes.

    One change of ground (no going back) and a reference never lost: the same poses, bit for
    bit, as with the blend switched off.
    """
    sim = _drive(mode)
    odometer, prediction, _ = _run(sim, _reference(sim, cut))
    assert odometer.counters['online_hold_blend'] == 0
    assert odometer.counters['online_change'] >= 1
    monkeypatch.setattr(HoldingBlend, '_hold_plan_now', lambda self: None)
    plain = _run(sim, _reference(sim, cut))[1]
    assert np.array_equal(prediction.poses, plain.poses)
    assert np.array_equal(prediction.pose_covariances, plain.pose_covariances)


@pytest.mark.ros
def test_n137_the_node_blends_while_holding_as_predict_does(tmp_path, alternating):
    """Publish from the real node what ``skidkin predict`` gives, the blend included.

    The alternating drive with its reference cut for 20 s: the same poses and covariances,
    bit for bit.
    """
    from skidkin_ros.core.drive import PoseTrack
    from skidkin_ros.core.odometry.config import write_params_file
    from skidkin_ros.core.rotation import quaternion_to_yaw, yaw_to_quaternion
    from node_harness import assert_online_replay_matches
    from skidkin_ros.node.replay import replay_through_node

    path = write_params_file(tmp_path / 'online.yaml', {**FILE, 'robot': 'sim_husky'},
                             {'source': 'test'})
    reference = _reference(alternating)
    wire_yaw = np.array([quaternion_to_yaw(*yaw_to_quaternion(float(v)))
                         for v in reference.yaw])
    odometer = online_odometer(OdometryConfig.from_file(path))
    expected = odometer.predict(alternating.wheels, reference=PoseTrack(
        reference.t_ns, reference.x, reference.y, wire_yaw))
    assert odometer.counters['online_hold_blend'] == 1
    assert odometer.counters['online_hold_dwell'] == 1   # the dwell model weighs the grounds
    result = replay_through_node(alternating.wheels, params_file=path, reference=reference,
                                 timeout_s=300.0)
    assert_online_replay_matches(result, expected, alternating.wheels)
    for cause in ('online_hold_blend', 'online_hold_dwell', 'online_switch',
                  'reference_accepted'):
        assert result.counters.get(cause, 0) == odometer.counters[cause]


def test_a_flicker_of_the_recognition_is_no_alternation():
    """Count as alternation only stays of a switch_window or more, and two returns."""
    odometer = online_odometer(OdometryConfig.from_flat(FILE))
    learner = odometer.learner
    old = learner.grounds[0]
    new = Ground(1, old.k * 0.8, old.prior.copy())
    learner.grounds.append(new)

    def plan(events, now):
        learner.active = next(g for at, g, c in events[::-1])
        learner._activations = collections.deque(events)
        learner.travel_m = now
        return learner._hold_plan_now()
    # a change, then a false switch back and forth within 0.3 m (long-stretch seed 32)
    assert plan([(0.0, old, 'start'), (43.2, new, 'online_change'),
                 (44.9, old, 'online_switch'), (45.2, new, 'online_switch')], 57.2) is None
    # one return after a long stay: a one-off, not a pattern
    assert plan([(0.0, old, 'start'), (30.0, new, 'online_change'),
                 (45.0, old, 'online_switch')], 57.0) is None
    # grounds alternating every 4 m: blended, occupancy about half each
    events = [(0.0, old, 'start'), (4.0, new, 'online_change')] + [
        (4.0 * i, (old, new)[i % 2], 'online_switch') for i in range(2, 15)]
    grounds, pi, mu = plan(events, 58.0)
    assert grounds[0] is learner.active and len(grounds) == 2
    assert pi == pytest.approx([0.5, 0.5], abs=0.1)
    assert mu == pytest.approx((7.5 / 30.0) / 0.5, rel=0.1)


def _no_choice(monkeypatch):
    monkeypatch.setattr(GyroChoice, '_gyro_weigh',
                        lambda self, t1_ns, plan, travel, weights: weights)


def _drift(sim, poses):
    """Return the pose error gained over the dropout, in metres."""
    truth = sim.truth.poses
    t = (sim.wheels.t_ns - sim.start_ns) * 1e-9
    i0, i1 = np.searchsorted(t, CUT_S[0]), np.searchsorted(t, CUT_S[1])
    return float(np.hypot(*((poses[i1] - poses[i0]) - (truth[i1] - truth[i0]))[:2]))


def test_the_gyro_weighs_the_grounds_while_holding(alternating, monkeypatch):
    """With a gyro, the blend follows the ground that explains the turning: less drift.

    The weights leave the chain's (the looks while turning), the covariance is the mixture's
    with them, and after the dropout the active ground's own parameters are in force again.
    """
    reference, imu = _reference(alternating), _gyro(alternating)
    odometer, prediction, seen = _run(alternating, reference, record=True, imu=imu)
    assert odometer.counters['online_hold_blend'] == 1
    assert odometer.counters['online_hold_dwell'] == 0   # the gyro's forward filter instead
    assert odometer.counters['online_hold_gyro'] > 100
    holding = [s for s in seen if CUT_S[0] + 1.5 < s[0] < CUT_S[1] and s[1] == 'holding']
    weights = np.array([s[2] for s in holding])
    # not the chain's monotone decay: the gyro moves the weights both ways, to near 0 and 1
    assert np.any(np.diff(weights) > 0.05) and np.any(np.diff(weights) < -0.05)
    assert weights.min() < 0.2 and weights.max() > 0.8
    for s in holding[::50]:
        (w, k, cov), ks, active_cov = s[5], s[7], s[8]
        assert w.sum() == pytest.approx(1.0) and np.all(w >= 0.0)
        assert np.all(k >= ks.min(axis=0) - 1e-12) and np.all(k <= ks.max(axis=0) + 1e-12)
        assert np.all(np.diag(cov) >= np.diag(active_cov) * min(w.max(), 1.0) * 0.999)
    after = [s for s in seen if s[0] > CUT_S[1] + 0.5]
    assert after and all(s[2] == 1.0 and s[5] is None for s in after)
    chosen = _drift(alternating, prediction.poses)
    _no_choice(monkeypatch)
    chain = _drift(alternating, _run(alternating, reference, imu=imu)[1].poses)
    assert chosen < 0.8 * chain


@pytest.mark.parametrize('mode, cut, gyro', [('time', CUT_S, True), ('alternate', None, True),
                                             ('alternate', CUT_S, False)])
def test_the_gyro_changes_nothing_without_a_blend_or_without_a_gyro(mode, cut, gyro,
                                                                    monkeypatch):
    """After one change of ground, while the reference comes, or with no gyro: bit for bit.

    The same poses and covariances as the chain's blend alone (the code before the gyro's
    weighing); the last case blends (grounds alternate, the reference is cut) with no gyro.
    """
    sim = _drive(mode)
    imu = _gyro(sim) if gyro else None
    odometer, prediction, _ = _run(sim, _reference(sim, cut), imu=imu)
    assert odometer.counters['online_hold_gyro'] == 0
    assert odometer.counters['online_hold_blend'] == (0 if gyro else 1)
    _no_choice(monkeypatch)
    plain = _run(sim, _reference(sim, cut), imu=imu)[1]
    assert np.array_equal(prediction.poses, plain.poses)
    assert np.array_equal(prediction.pose_covariances, plain.pose_covariances)


def test_n151_a_gyro_that_stops_during_the_dropout(alternating):
    """The gyro stops 5 s into the dropout: the chain alone carries the weights from there.

    No error; the looks stop; from then on the weights move only toward the recent shares (the
    chain's decay from where the gyro left them), and the drift stays finite.
    """
    reference = _reference(alternating)
    stop = CUT_S[0] + 5.0
    full, _, _ = _run(alternating, reference, imu=_gyro(alternating))
    odometer, prediction, seen = _run(alternating, reference, record=True,
                                      imu=_gyro(alternating, stop_s=stop))
    assert 0 < odometer.counters['online_hold_gyro'] < full.counters['online_hold_gyro']
    assert np.all(np.isfinite(prediction.poses))
    late = [s for s in seen if stop + 1.0 < s[0] < CUT_S[1] and s[1] == 'holding']
    weights = np.array([s[2] for s in late])
    # the chain's decay from where the gyro left them: monotone, toward the recent shares
    steps = np.diff(weights)
    assert len(late) > 200 and np.any(steps != 0.0)
    assert np.all(steps <= 1e-12) or np.all(steps >= -1e-12)


@pytest.mark.ros
def test_n152_the_node_weighs_the_grounds_by_the_gyro_as_predict_does(tmp_path, alternating):
    """Publish from the real node (gyro fused) what ``skidkin predict`` gives while holding.

    The alternating drive with its reference cut for 20 s and a biased gyro: the gyro weighs
    the grounds in both, with the same poses and covariances.
    """
    from skidkin_ros.core.drive import PoseTrack, WheelSamples
    from skidkin_ros.core.odometry.config import write_params_file
    from skidkin_ros.core.rotation import quaternion_to_yaw, yaw_to_quaternion
    from node_harness import assert_online_replay_matches
    from skidkin_ros.node.replay import replay_through_node

    imu = _gyro(alternating)
    keep = alternating.wheels.t_ns <= imu.t_ns[-1] - 100_000_000   # the gyro outlasts them
    wheels = WheelSamples(alternating.wheels.t_ns[keep], alternating.wheels.omega_l[keep],
                          alternating.wheels.omega_r[keep])
    path = write_params_file(tmp_path / 'online.yaml',
                             {**FILE, 'robot': 'sim_husky', 'imu.mode': 'fuse'},
                             {'source': 'test'})
    reference = _reference(alternating)
    wire_yaw = np.array([quaternion_to_yaw(*yaw_to_quaternion(float(v)))
                         for v in reference.yaw])
    odometer = online_odometer(OdometryConfig.from_file(path))
    expected = odometer.predict(wheels, imu=imu, reference=PoseTrack(
        reference.t_ns, reference.x, reference.y, wire_yaw))
    assert odometer.counters['online_hold_blend'] == 1
    assert odometer.counters['online_hold_dwell'] == 0   # the gyro's forward filter instead
    assert odometer.counters['online_hold_gyro'] > 100
    result = replay_through_node(wheels, params_file=path, reference=reference, imu=imu,
                                 timeout_s=300.0)
    assert_online_replay_matches(result, expected, wheels)
    for cause in ('online_hold_blend', 'online_hold_gyro', 'online_switch', 'reference_accepted'):
        assert result.counters.get(cause, 0) == odometer.counters[cause]


def test_the_dwell_model_follows_the_stays_seen():
    """Stays of about 4 m, 3 m spent on the last one: the other ground next, then back."""
    stays = [(j % 2, length) for j, length in enumerate((4.0, 4.2, 3.8, 4.1, 3.9, 4.0))]
    switches = [(j % 2, 1 - j % 2) for j in range(6)]
    table = dwell.occupancy(stays, switches, 2, 3.0, 0.5)
    assert np.all(table >= 0.0) and np.allclose(table.sum(axis=0), 1.0)
    at = {d: dwell.weights_at(table, d)[0] for d in (0.0, 0.3, 2.0, 5.5, 1e3)}
    assert at[0.0] == pytest.approx(1.0) and at[0.3] > 0.8
    assert at[2.0] < 0.2     # left the last ground about 1 m in, on the other for about 4 m
    assert at[5.5] > 0.7     # back on the last ground
    assert 0.3 < at[1e3] < 0.7   # far on: the shares
    # just entered the last ground: it holds for the first metres
    fresh = dwell.occupancy(stays, switches, 2, 0.0, 0.5)
    assert dwell.weights_at(fresh, 2.5)[0] > 0.8
    # long stays on ground 0, short ones on ground 1: the long-run shares follow the lengths
    uneven = [(j % 2, (6.0, 2.0)[j % 2] + 0.1 * j) for j in range(8)]
    far = dwell.occupancy(uneven, switches, 2, 1.0, 0.5)[0, -150:].mean()   # 35-50 m
    assert far == pytest.approx(6.3 / (6.3 + 2.4), abs=0.04)
    # stays of any length (spread widely): less sure than the regular ones, 1 + 2 m in
    assert dwell.weights_at(dwell.occupancy(stays, switches, 2, 1.0, 0.5), 2.0)[0] > 0.85
    spread = [(j % 2, length) for j, length in enumerate((1.2, 6.5, 2.8, 5.1, 3.6, 7.0, 1.9))]
    wide = dwell.weights_at(dwell.occupancy(spread, switches, 2, 1.0, 0.5), 2.0)
    assert 0.2 < wide[0] < 0.6
    assert dwell.occupancy([], [], 2, 3.0, 0.5) is None
    # the dwell laws are used only where they predict the stays (left out) better than a
    # memoryless law: regular stays yes; stays of no typical length or a single one, no
    assert dwell.lengths_explained(stays, 0.5)
    irregular = [(j % 2, length) for j, length in enumerate((0.6, 5.2, 1.1, 9.0, 2.0, 0.9, 3.9,
                                                             12.5))]
    assert not dwell.lengths_explained(irregular, 0.5)
    assert not dwell.lengths_explained([(0, 4.0)], 0.5)


def test_the_dwell_model_while_holding(alternating, monkeypatch):
    """Where grounds alternate with stays of a typical length, weigh them by the dwell model.

    The weights leave the chain's monotone decay (the robot is expected back on the last
    ground after a stay on the other), the covariance is still the mixture's, and the drift
    over the dropout is smaller than the chain's alone on this drive.
    """
    reference = _reference(alternating)
    odometer, prediction, seen = _run(alternating, reference, record=True)
    assert odometer.counters['online_hold_blend'] == odometer.counters['online_hold_dwell'] == 1
    holding = [s for s in seen if CUT_S[0] + 1.5 < s[0] < CUT_S[1] and s[1] == 'holding']
    weights = np.array([s[2] for s in holding])
    assert np.any(np.diff(weights) > 0.02) and np.any(np.diff(weights) < -0.02)
    for s in holding[::50]:
        (w, k, _), ks = s[5], s[7]
        assert w.sum() == pytest.approx(1.0) and np.all(w >= 0.0)
        assert np.all(k >= ks.min(axis=0) - 1e-12) and np.all(k <= ks.max(axis=0) + 1e-12)
    after = [s for s in seen if s[0] > CUT_S[1] + 0.5]
    assert after and all(s[2] == 1.0 and s[5] is None for s in after)
    with_dwell = _drift(alternating, prediction.poses)
    monkeypatch.setattr(HoldingBlend, '_dwell_plan', lambda self, grounds: None)
    chain = _drift(alternating, _run(alternating, reference)[1].poses)
    assert with_dwell < chain


def test_c247_stretches_of_random_length_and_a_bad_spread():
    """terrain_regime alternate with period_spread: stretches drawn within period_m (1 +- s).

    Each drive seed draws its own lengths, the same for every prefix of a drive; a spread out
    of [0, 1) is refused with what was expected.
    """
    from skidkin_ros.errors import ParameterError
    from skidkin_ros.sim.effects import _alternating, EffectInput

    n = 20001
    t = np.linspace(0.0, 200.0, n)
    data = EffectInput(t, np.zeros(n), np.zeros(n), np.tile([0.5, 0.0, 0.0], (n, 1)), None,
                       200.0)     # 100 m of path at 0.5 m/s

    def stretches(mask):
        edges = np.flatnonzero(np.diff(mask.astype(int))) + 1
        return np.diff(edges) * 0.5 * (t[1] - t[0])
    fixed = stretches(_alternating(data, 4.0))
    assert np.allclose(fixed, 4.0, atol=0.02)
    drawn = stretches(_alternating(data, 4.0, 0.5, seed=7))
    assert drawn.min() >= 2.0 - 0.02 and drawn.max() <= 6.0 + 0.02 and drawn.std() > 0.5
    other = stretches(_alternating(data, 4.0, 0.5, seed=8))
    assert not np.array_equal(drawn[:5], other[:5])
    half = EffectInput(t[:n // 2], data.omega_l[:n // 2], data.omega_r[:n // 2],
                       data.twist[:n // 2], None, 200.0)
    assert np.array_equal(_alternating(half, 4.0, 0.5, seed=7),
                          _alternating(data, 4.0, 0.5, seed=7)[:n // 2])
    for bad in (-0.1, 1.0, 2.5):
        with pytest.raises(ParameterError, match=r'period_spread must be >= 0 and < 1'):
            make_effect('terrain_regime', 0.25, mode='alternate', period_spread=bad)


def test_c253_a_last_stay_far_longer_than_any_seen_still_ends():
    """Stays of about 1 m, then tens of metres on the last ground before the loss.

    Far beyond every stay seen the stay-length law is its memoryless share alone, so the
    chances ahead are the same for 20 m or 60 m spent (an exponential forgets the past); the
    table must stay finite and a stay longer than any seen must still end.
    """
    stays = [(j % 2, length) for j, length in enumerate((1.0, 1.1, 0.9, 1.0, 1.05, 0.95))]
    switches = [(j % 2, 1 - j % 2) for j in range(6)]
    near = dwell.occupancy(stays, switches, 2, 20.0, 0.5)
    assert np.all(np.isfinite(near))
    for elapsed in (35.0, 60.0, 500.0, 1e5):
        far = dwell.occupancy(stays, switches, 2, elapsed, 0.5)
        assert np.all(np.isfinite(far)), elapsed
        assert np.allclose(far, near, atol=1e-9), elapsed
        weights = dwell.weights_at(far, 0.0)
        assert weights[0] == pytest.approx(1.0)
        assert 0.1 < dwell.weights_at(far, 1.0)[0] < 0.7   # it ends within a metre or so
