"""The ground-truth guard: ICP judged by its own quality, the IMU, and the wheels for gross errors.

No robot geometry is needed; skid and slip keep their ground truth. Real
kiss-icp on simulated scans.
"""

from __future__ import annotations

import numpy as np
import pytest

from skidkin_ros.adapters.lidar_gt import IcpConfig, lidar_ground_truth
from skidkin_ros.adapters.lidar_guard import flag_poses, GuardLimits
from skidkin_ros.core.drive import ImuSamples, WheelSamples
from skidkin_ros.errors import ParameterError
from skidkin_ros.sim import LidarConfig, make_effect, SimConfig, simulate
from skidkin_ros.sim.accuracy import increment_errors

LIDAR = LidarConfig(azimuth_resolution_deg=0.5, mount_xyz_m=(0.3, 0.1, 0.5), mount_yaw_rad=0.4)
ICP = IcpConfig(voxel_size_m=0.5, max_range_m=50.0)


@pytest.mark.heavy
def test_strong_skid_and_slip_keep_their_correct_ground_truth():
    # The body skids sideways (v_y = 0.12 v w), lags the wheels (first-order, 0.3 s: the body
    # is slower than the wheels while they accelerate) and slips with speed: the frames where
    # wheels and body disagree most are the ones a diagnosis needs. The guard used before
    # (ideal wheel odometry of the true geometry, +-0.1 m + 50 %) excluded 34 of these 300
    # correct poses (11 %); ICP's own quality and the IMU keep them.
    effects = (make_effect('lateral_skid', 0.12), make_effect('first_order_lag', 0.3),
               make_effect('speed_slip', 0.3))
    sim = simulate(SimConfig(duration_s=30.0, seed=9, lidar=LIDAR, internal_rate_hz=200.0,
                             effects=effects))
    result = lidar_ground_truth(sim.scans(), LIDAR.extrinsic(), ICP, wheels=sim.wheels,
                                imu=sim.imu)
    track = result.track
    # the ICP is right everywhere, including where the wheels disagree ...
    assert increment_errors(track, sim.pose_at, horizon_s=1.0, valid_only=False).percentile(
        95)[0] < 0.05
    # ... and the wheels do disagree: over 1 s the wheel-implied forward travel misses the
    # true one by more than 10 cm in a tenth of the windows
    truth = sim.truth_at(sim.wheels.t_ns)
    step = np.searchsorted(truth.t_ns, truth.t_ns + 10**9)
    ok = step < len(truth)
    true_travel = np.hypot(truth.x[step[ok]] - truth.x[ok], truth.y[step[ok]] - truth.y[ok])
    held = np.concatenate([[0.0], np.cumsum(0.5 * (sim.wheels.omega_l + sim.wheels.omega_r)[:-1]
                                            * np.diff(sim.wheels.t_ns) * 1e-9)])
    wheel_travel = 0.1651 * np.abs(held[step[ok]] - held[ok])
    assert np.percentile(np.abs(wheel_travel - true_travel), 90) > 0.10
    # kept: all but a handful
    assert track.valid.mean() >= 0.99, result.excluded
    assert 'no geometry needed' in result.excluded['checks']['wheels']
    assert result.excluded['checks']['imu_yaw'].startswith('on')


def _straight_track(n: int = 200, speed: float = 1.0, rate_hz: float = 10.0):
    t_ns = (np.arange(n) * 1e9 / rate_hz).astype(np.int64)
    t_s = t_ns * 1e-9
    yaw = 0.2 * np.sin(0.5 * t_s)
    x = np.cumsum(np.concatenate([[0.0], speed / rate_hz * np.cos(yaw[:-1])]))
    y = np.cumsum(np.concatenate([[0.0], speed / rate_hz * np.sin(yaw[:-1])]))
    return t_ns, x, y, yaw


def _imu_of(t_ns, yaw):
    imu_t = np.arange(t_ns[0], t_ns[-1] + 1, 10_000_000, dtype=np.int64)
    rate = np.gradient(np.interp(imu_t, t_ns, yaw), imu_t * 1e-9)
    return ImuSamples(imu_t, rate)


def test_icp_yaw_that_leaves_the_gyro_is_flagged_only_with_an_imu():
    t_ns, x, y, yaw = _straight_track()
    icp_yaw = yaw.copy()
    icp_yaw[100:] += 0.15  # one ICP increment turned 0.15 rad too far (a wrong match)
    quality = np.tile([0.95, 0.02, 0.3], (t_ns.size, 1))
    frames = list(range(t_ns.size))
    status = ['ok'] * t_ns.size
    args = (t_ns, x, y, icp_yaw, np.zeros(t_ns.size), quality, frames, status, GuardLimits())
    reasons, excluded = flag_poses(*args, imu=_imu_of(t_ns, yaw))
    flagged = [i for i, r in enumerate(reasons) if r]
    # the poses whose last-second window holds the wrong increment
    assert set(flagged) == set(range(100, 110)) and excluded.by_reason == {'imu_yaw': 10}
    reasons, excluded = flag_poses(*args)
    assert not any(reasons) and excluded.checks['imu_yaw'] == 'off: no IMU'


def test_poor_registration_quality_is_flagged_by_its_own_numbers():
    t_ns, x, y, yaw = _straight_track(50)
    quality = np.tile([0.95, 0.02, 0.3], (t_ns.size, 1))
    quality[10, 0] = 0.3  # few correspondences
    quality[20, 1] = 0.2  # residual 10x the recording's median
    quality[30, 2] = 0.01  # degenerate geometry
    quality[0] = np.nan  # the first frame is not measured, and not judged
    reasons, excluded = flag_poses(t_ns, x, y, yaw, np.zeros(t_ns.size), quality,
                                   list(range(t_ns.size)), ['ok'] * t_ns.size, GuardLimits())
    assert {i: r for i, r in enumerate(reasons) if r} == {
        10: 'icp_inliers', 20: 'icp_residual', 30: 'icp_degenerate'}
    assert excluded.invalid == 3 and excluded.seconds_excluded == pytest.approx(0.3)
    assert '3 of 50 poses excluded' in excluded.summary()


def test_wheel_check_needs_no_geometry_and_catches_only_gross_errors():
    t_ns, x, y, yaw = _straight_track(300)
    wheel_t = np.arange(t_ns[0], t_ns[-1] + 1, 50_000_000, dtype=np.int64)
    # wheels of any radius: 1 m/s is 6.06 rad/s on a Husky, 3.33 on a Warthog
    for omega in (6.06, 3.33):
        speed = np.full(wheel_t.size, omega)
        # 20 % slip all along: within the gross limits
        slipping = WheelSamples(wheel_t, 1.2 * speed, 1.2 * speed)
        args = (t_ns, x, y, yaw, np.zeros(t_ns.size), np.full((t_ns.size, 3), np.nan),
                list(range(t_ns.size)), ['ok'] * t_ns.size, GuardLimits())
        reasons, excluded = flag_poses(*args, wheels=slipping)
        assert not any(reasons), excluded.as_dict()
        # the wheels stopped for 2 s while ICP drove on at 1 m/s: gross
        stuck = speed.copy()
        stuck[(wheel_t - wheel_t[0] > 10e9) & (wheel_t - wheel_t[0] < 12e9)] = 0.0
        reasons, excluded = flag_poses(*args, wheels=WheelSamples(wheel_t, stuck, stuck))
        flagged_t = np.array([t_ns[i] for i, r in enumerate(reasons) if r]) * 1e-9
        assert excluded.by_reason.get('wheel_gross', 0) >= 10
        assert flagged_t.min() > 10.0 and flagged_t.max() < 13.1


def test_guard_limits_reject_nonsense():
    with pytest.raises(ParameterError, match='max_gap_factor'):
        GuardLimits(max_gap_factor=1.0)
    with pytest.raises(ParameterError, match='window_s'):
        GuardLimits(window_s=0.0)


def test_a_gyro_spike_does_not_flag_correct_icp_poses():
    """C104: the guard takes the gyro as the node does (one rule, core/odometry/gyro.py).

    A lone 20 rad/s sample (under the 35 rad/s saturation) is a glitch the node skips (imu.spike);
    the guard integrated it as held for 10 ms (0.2 rad in every window over it) and flagged
    correct ICP poses.
    """
    t_ns, x, y, yaw = _straight_track()
    imu = _imu_of(t_ns, yaw)
    rate = imu.yaw_rate.copy()
    rate[1000] = 20.0
    quality = np.tile([0.95, 0.02, 0.3], (t_ns.size, 1))
    args = (t_ns, x, y, yaw, np.zeros(t_ns.size), quality, list(range(t_ns.size)),
            ['ok'] * t_ns.size, GuardLimits())
    reasons, excluded = flag_poses(*args, imu=ImuSamples(imu.t_ns, rate))
    assert not any(reasons), excluded.by_reason
