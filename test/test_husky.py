"""The real Husky A200 windows (DRIVE dataset): the five models and the virtual track width."""

from pathlib import Path

import pytest

from skidkin_ros.adapters.table import read_table
from skidkin_ros.core.calibration.holdout import split_holdout
from skidkin_ros.core.calibration.pipeline import (calibrate, calibrate_interval,
                                                   CalibrationOptions, choose_interval,
                                                   result_to_parameters)
from skidkin_ros.core.kinematics.specs import Geometry

DATA = Path(__file__).resolve().parents[1] / 'data' / 'husky' / 'drive_husky_windows.csv'
HUSKY = Geometry(0.1651, 0.555)


@pytest.mark.skipif(not DATA.is_file(), reason='Husky table not available')
def test_husky_calibration():
    train, evaluate = split_holdout(read_table(DATA), every=2, key='calib_step')
    assert len(train) + len(evaluate) == 603
    result = calibrate(train, evaluate, HUSKY, CalibrationOptions())
    assert all(fit.valid for fit in result.fits.values()), result.warnings
    ideal = result.evaluation['ideal_dd']
    for name in ('edd_symmetric', 'edd_asymmetric', 'roc', 'full_linear'):
        ev = result.evaluation[name]
        # trained models: far better heading than the ideal differential drive
        assert ev.stats_theta.median < 0.25 * ideal.stats_theta.median
        assert ev.stats_t.median < 0.6 * ideal.stats_t.median
    fit = result.fits['edd_symmetric']
    ratio = fit.values['b_hat'] / HUSKY.track_width
    # the skid-steer Husky turns as if its wheels were about twice as far apart
    # (Clearpath ships wheel_separation_multiplier = 1.875)
    assert 1.7 < ratio < 2.5
    assert 0.8 < fit.values['alpha'] < 0.95
    assert result.best in result.scores
    # Skid errors are heavier-tailed than a Gaussian: the rates are scaled up to cover them, and
    # the share inside the 95 % region, counted on segments the rates were not fitted on, is ~95 %.
    for name in ('edd_symmetric', 'edd_asymmetric', 'roc', 'full_linear'):
        noise = result.noise[name]
        assert noise.coverage_scale > 1.2, name
        assert 0.93 <= noise.consistency.inside_95_3dof <= 0.98, name


@pytest.mark.heavy
@pytest.mark.skipif(not DATA.is_file(), reason='Husky table not available')
def test_husky_encoder_speeds_describe_the_interval_that_ends_at_their_stamp():
    train, evaluate = split_holdout(read_table(DATA), every=2, key='calib_step')
    options = CalibrationOptions(models=('edd_symmetric',), n_starts=2)
    result = calibrate_interval(train, evaluate, HUSKY, options)
    assert result.options.interval == 'ending', result.interval_errors
    ending, starting = result.interval_errors['ending'], result.interval_errors['starting']
    # iterated fit, edd_symmetric: 0.211 -> 0.199 m/m, 7.81 -> 7.57 deg/m (Sigma = identity:
    # 0.206 -> 0.195, 8.41 -> 7.53)
    assert ending[0] < 0.97 * starting[0] and ending[1] < starting[1]
    assert result_to_parameters(result)['interval'] == 'ending'


def test_the_interval_rule_keeps_ending_within_the_tie_tolerance():
    assert choose_interval({'ending': (0.101, 1.0), 'starting': (0.1, 1.0),
                            'midpoint': (0.2, 2.0)})[0] == 'ending'
    assert choose_interval({'ending': (0.2, 1.2), 'starting': (0.2, 1.2),
                            'midpoint': (0.1, 1.0)})[0] == 'midpoint'
    nan = float('nan')
    assert choose_interval({'ending': (nan, 1.0), 'starting': (0.2, 1.2)})[0] == 'starting'


@pytest.mark.skipif(not DATA.is_file(), reason='Husky table not available')
def test_husky_gyro_calibration_and_fuse():
    from skidkin_ros.core.calibration.gyro_fit import evaluate_gyro_mode
    from skidkin_ros.core.calibration.pipeline import result_to_parameters
    from skidkin_ros.core.calibration.segments import cut_segments, SegmentOptions
    from skidkin_ros.core.odometry.config import OdometryConfig

    train, evaluate = split_holdout(read_table(DATA), every=2, key='calib_step')
    result = calibrate(train, evaluate, HUSKY, CalibrationOptions(models=('edd_symmetric',)))
    gyro = result.gyro
    # the Husky's gyro: scale ~1, tiny bias, stamps ~172 ms early against the ICP / wheel clock
    assert gyro.scale == pytest.approx(1.0, abs=0.01)
    assert abs(gyro.bias) < 2e-3
    assert -0.20 < gyro.time_offset < -0.15
    config = OdometryConfig.from_flat(result_to_parameters(result))
    assert config.imu.mode == 'off' and config.imu.time_offset == gyro.time_offset
    segments = cut_segments(evaluate, SegmentOptions(horizon_m=2.0))
    scores = {mode: evaluate_gyro_mode(config, evaluate, segments, 'edd_symmetric', mode)
              for mode in ('off', 'adapt', 'fuse')}
    off, adapt, fuse = (scores[m].evaluation for m in ('off', 'adapt', 'fuse'))
    assert off.stats_theta.median == pytest.approx(
        result.evaluation['edd_symmetric'].stats_theta.median, rel=1e-6)
    # the goal: heading at least 3x better with fuse, translation not worse
    assert fuse.stats_theta.median < off.stats_theta.median / 3
    assert fuse.stats_t.median <= 1.05 * off.stats_t.median
    assert adapt.stats_theta.median < 0.7 * off.stats_theta.median
    assert scores['fuse'].end_yaw_deg.median < scores['off'].end_yaw_deg.median / 3
