"""``skidkin predict --reference``: a bag's reference topic through the learning odometer."""

import csv

import numpy as np
from reference_bag import write_reference_bag
from skidkin_ros.adapters.bag_reader import open_recording
from skidkin_ros.cli.main import main
from skidkin_ros.core.odometry.config import OdometryConfig, write_params_file
from skidkin_ros.core.online import online_odometer
from skidkin_ros.sim.effects import make_effect
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate

FILE = {'model': 'edd_asymmetric', 'robot': 'sim',
        **{f'models.edd_asymmetric.{k}': v for k, v in DEFAULT_TRUE_PARAMS.items()},
        'models.edd_asymmetric.noise.calibrated': True}


def _bag(tmp_path, sim):
    reference = sim.truth_at(np.arange(sim.start_ns, sim.end_ns, 100_000_000))
    return write_reference_bag(tmp_path / 'drive', sim.wheels, '/kiss/odometry', reference,
                               'odom_lidar', 'base_link')


def test_predict_with_a_reference_learns_as_the_odometer_does(tmp_path, capsys):
    effect = make_effect('terrain_regime', 0.25, mode='time', switch_frac=0.3, yaw=0.1)
    sim = simulate(SimConfig(duration_s=60.0, seed=12, effects=(effect,)))
    bag = _bag(tmp_path, sim)
    params = write_params_file(tmp_path / 'file.yaml', FILE, {'source': 'test'})
    out = tmp_path / 'pred.csv'
    assert main(['predict', str(bag), '--params', str(params), '--reference', '/kiss/odometry',
                 '--out', str(out)]) == 0
    assert 'online calibration:' in capsys.readouterr().out
    fixed_out = tmp_path / 'fixed.csv'
    assert main(['predict', str(bag), '--params', str(params), '--out', str(fixed_out)]) == 0
    with out.open() as handle:
        rows = list(csv.DictReader(handle))
    with fixed_out.open() as handle:
        fixed = list(csv.DictReader(handle))
    # the same object offline: the odometer with online calibration, the reference as read
    config = OdometryConfig.from_flat({**OdometryConfig.from_file(params).values,
                                       'online.enabled': True})
    with open_recording(bag) as recording:
        reference = recording.read_pose_track('/kiss/odometry')
    expected = online_odometer(config).predict(sim.wheels, reference=reference)
    got = np.array([[float(r['x']), float(r['y'])] for r in rows])
    np.testing.assert_allclose(got, expected.poses[:, :2], rtol=0, atol=1e-9)
    # learning moved it: on the new ground the file's odometry goes elsewhere
    end_fixed = np.array([float(fixed[-1]['x']), float(fixed[-1]['y'])])
    truth_end = sim.truth.poses[-1, :2]
    assert np.hypot(*(got[-1] - truth_end)) < 0.75 * np.hypot(*(end_fixed - truth_end))


def test_predict_reference_refuses_a_table(tmp_path, capsys):
    table = tmp_path / 'table.csv'
    table.write_text('t,x,y,yaw,omega_l,omega_r\n0,0,0,0,1,1\n')
    params = write_params_file(tmp_path / 'file.yaml', FILE, {'source': 'test'})
    code = main(['predict', str(table), '--params', str(params), '--reference', 'x',
                 '--out', str(tmp_path / 'o.csv')])
    assert code != 0
    assert '--reference needs a bag' in capsys.readouterr().err
