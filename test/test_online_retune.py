"""Runtime changes of online.* through the real node: gates keep what was learned."""

import numpy as np
import pytest
from skidkin_ros.core.drive import PoseTrack
from skidkin_ros.core.odometry.config import write_params_file
from skidkin_ros.core.online.retune import KEEP
from skidkin_ros.sim.effects import make_effect
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate

pytestmark = pytest.mark.ros

FILE = {'model': 'edd_asymmetric', 'robot': 'sim_husky',
        **{f'models.edd_asymmetric.{k}': v for k, v in DEFAULT_TRUE_PARAMS.items()},
        'models.edd_asymmetric.noise.calibrated': True, 'online.enabled': True}


def test_a_gate_changed_at_runtime_keeps_what_was_learned(make_rig, tmp_path):
    from rclpy.parameter import Parameter
    rig = make_rig(params_file=write_params_file(tmp_path / 'p.yaml', FILE))
    node = rig.node
    learner = node._odometer.learner
    file_k = learner.k0.copy()
    # the node's own odometer learns a ground change (slip 25 %) from a reference
    sim = simulate(SimConfig(duration_s=40.0, seed=3, effects=(
        make_effect('terrain_regime', 0.25, mode='time', switch_frac=0.3, yaw=0.1),)))
    truth = sim.truth_at(np.arange(sim.start_ns, sim.end_ns, 100_000_000))
    with node._lock:
        node._odometer.predict(sim.wheels, reference=PoseTrack(truth.t_ns, truth.x, truth.y,
                                                               truth.yaw))
    learned = learner.k.copy()
    grounds = len(learner.grounds)
    assert learner.counters['online_segments'] >= 8 and not np.allclose(learned, file_k)
    for name, value in (('online.max_rate', 20.0), ('online.cusum_threshold', 60.0),
                        ('online.delay_tolerance', 0.1)):
        result = node.set_parameters([Parameter(name, value=value)])[0]
        assert result.successful, result.reason
        assert node._odometer.learner is learner          # kept, with what it learned
        assert np.array_equal(learner.k, learned) and len(learner.grounds) == grounds
        assert getattr(learner.params, name.removeprefix('online.')) == value
    assert learner._min_period_ns == pytest.approx(1e9 / 20.0)
    assert learner._delay.tolerance_s == 0.1
    # a parameter that invalidates it (the segments are cut by horizon): learning restarts
    result = node.set_parameters([Parameter('online.horizon', value=3.0)])[0]
    assert result.successful, result.reason
    fresh = node._odometer.learner
    assert fresh is not learner and np.array_equal(fresh.k, file_k)
    assert fresh.params.max_rate == 20.0 and fresh.params.horizon == 3.0
    assert 'horizon' not in KEEP and 'time_offset' not in KEEP
