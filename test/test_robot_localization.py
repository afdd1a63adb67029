"""The real node's odometry meets what robot_localization's ekf_node needs (ekf_skidkin.yaml).

robot_localization cannot be installed here, so its expectations are checked on the messages:
frames equal to the EKF's odom_frame / base_link_frame, symmetric positive-definite pose and twist
covariances, no zero variance on a fused field (odom0_config), stamps non-zero and increasing.
Both the fallback diagonals (no calibration) and the calibrated, propagated covariance.
"""

from pathlib import Path

from node_harness import NodeRig, NS_PER_S, wall_ns
import numpy as np
import pytest
import yaml

pytestmark = pytest.mark.ros

CONFIG = Path(__file__).resolve().parents[1] / 'config'
FIELDS = ('x', 'y', 'z', 'roll', 'pitch', 'yaw', 'vx', 'vy', 'vz', 'vroll', 'vpitch', 'vyaw',
          'ax', 'ay', 'az')
CALIBRATED = {
    'model': 'edd_symmetric',
    'models.edd_symmetric.alpha': 0.9,
    'models.edd_symmetric.b_hat': 1.1,
    'models.edd_symmetric.noise.calibrated': True,
    'models.edd_symmetric.noise.var_x_per_m': 2e-4,
    'models.edd_symmetric.noise.var_y_per_m': 1e-4,
    'models.edd_symmetric.noise.var_yaw_per_m': 5e-4,
    'models.edd_symmetric.noise.var_yaw_per_rad': 2e-3,
}


def _ekf_config():
    data = yaml.safe_load((CONFIG / 'ekf_skidkin.yaml').read_text())
    return data['ekf_filter_node']['ros__parameters']


def _wheel_script():
    """Standstill, forward, arc, spin, backward and standstill again: (omega_l, omega_r) rad/s."""
    phases = [(0.0, 0.0), (4.0, 4.0), (2.0, 5.0), (-3.0, 3.0), (-2.0, -2.5), (0.0, 0.0)]
    return [speeds for speeds in phases for _ in range(12)]


def _run_node(overrides):
    rig = NodeRig(overrides, params_file=str(CONFIG / 'odom_node.yaml'))
    try:
        t0 = wall_ns() - 30 * NS_PER_S
        for i, (omega_l, omega_r) in enumerate(_wheel_script()):
            rig.send_joint(t0 + i * 50_000_000, omega_l, omega_r)
        rig.drain()
        return list(rig.odom), rig.node.config
    finally:
        rig.close()


def _check_spd(matrix, what):
    assert np.all(np.isfinite(matrix)), what
    np.testing.assert_allclose(matrix, matrix.T, rtol=0, atol=1e-15, err_msg=what)
    assert np.linalg.eigvalsh(matrix).min() > 0.0, f'{what} is not positive definite'


def test_ekf_config_fuses_velocities_in_2d_with_frames_of_the_shipped_node_config():
    ekf = _ekf_config()
    node = yaml.safe_load((CONFIG / 'odom_node.yaml').read_text())['/**']['ros__parameters']
    assert ekf['two_d_mode'] is True
    assert ekf['odom_frame'] == node['odom_frame_id'] == ekf['world_frame']
    assert ekf['base_link_frame'] == node['base_frame_id']
    fused = {name for name, on in zip(FIELDS, ekf['odom0_config']) if on}
    assert len(ekf['odom0_config']) == 15
    assert fused == {'vx', 'vy', 'vyaw'}     # velocities only: the pose is their integral
    assert ekf['odom0_differential'] is False
    assert node['publish_tf'] is False and ekf['publish_tf'] is True   # one TF owner


@pytest.mark.parametrize('calibrated', [False, True], ids=['fallback', 'calibrated'])
def test_node_messages_meet_robot_localization_expectations(calibrated):
    ekf = _ekf_config()
    messages, config = _run_node(CALIBRATED if calibrated else {})
    assert len(messages) == len(_wheel_script())   # one per sample, none dropped
    fused = [i for i, on in enumerate(ekf['odom0_config']) if on]
    stamps = []
    pose_xx = []
    for msg in messages:
        assert msg.header.frame_id == ekf['odom_frame']
        assert msg.child_frame_id == ekf['base_link_frame']
        stamp = msg.header.stamp.sec * NS_PER_S + msg.header.stamp.nanosec
        assert stamp > 0
        stamps.append(stamp)
        pose_cov = np.asarray(msg.pose.covariance).reshape(6, 6)
        twist_cov = np.asarray(msg.twist.covariance).reshape(6, 6)
        _check_spd(pose_cov, 'pose covariance')
        _check_spd(twist_cov, 'twist covariance')
        for index in fused:
            assert index < 12, f'{FIELDS[index]} is not in nav_msgs/Odometry'
            cov = pose_cov if index < 6 else twist_cov
            assert cov[index % 6, index % 6] > 0.0, f'zero variance on fused {FIELDS[index]}'
        pose_xx.append(pose_cov[0, 0])
    assert np.all(np.diff(stamps) > 0), 'stamps must increase strictly'
    if calibrated:
        assert config.active_noise is not None
        # the propagated covariance grows with the motion, and stays put at standstill
        assert pose_xx[-1] > 100 * pose_xx[0]
        assert pose_xx[-1] == pytest.approx(pose_xx[-6], rel=1e-9)
        # the twist variance follows the motion (rate model), floored at standstill
        vx_var = [np.asarray(m.twist.covariance)[0] for m in messages]
        assert max(vx_var) > 10 * min(vx_var) > 0.0
    else:
        assert config.active_noise is None
        diag = np.asarray(config['pose_covariance_diagonal'])
        np.testing.assert_allclose(np.diag(np.asarray(messages[-1].pose.covariance)
                                           .reshape(6, 6)), diag)
        np.testing.assert_allclose(
            np.diag(np.asarray(messages[-1].twist.covariance).reshape(6, 6)),
            np.asarray(config['twist_covariance_diagonal']))
