"""The gyro study on the simulator (issue 14's goals), sized down: one drive per case."""

import math

import pytest
from skidkin_ros.studies.imu import calibrated_config, run_case


@pytest.mark.heavy
def test_adapt_recovers_on_a_new_ground_and_costs_nothing_without_one():
    config = calibrated_config()
    reference = calibrated_config('new ground')
    plain = run_case('effect-free', config, config, seeds=(11,), duration_s=120.0)
    change = run_case('ground change', config, reference, seeds=(11,), duration_s=120.0)
    every = plain.groups['all']
    # effect-free: adapt not worse than the fixed model by more than 5 % (heading and position)
    assert every['adapt'][1].median <= 1.05 * every['off'][1].median
    assert every['adapt'][0].median <= 1.05 * every['off'][0].median
    # fuse's heading: far better than the wheels'
    assert every['fuse'][1].median < every['off'][1].median / 3
    settled = change.groups['on the new ground, settled']
    true_theta = settled['true'][1].median
    assert settled['off'][1].median > 10 * true_theta          # the fixed model is far off
    assert settled['adapt'][1].median <= 1.5 * true_theta      # adapt is within 1.5x
    assert change.recovery_m and max(change.recovery_m) <= 5.0
    # the NEES at 2 m is finite and not over-confident in either gyro mode
    for mode in ('adapt', 'fuse'):
        mean, band, _ = plain.nees[mode]
        assert math.isfinite(mean) and mean <= band[1]
