"""The gyro study on the simulator (issue 14's goals), sized down: one drive per case.

The study calibrates and scores under ``interval: midpoint`` (exact for the simulator's speeds).
"""

import math

import pytest
from skidkin_ros.studies.imu import calibrated_config, run_case


@pytest.fixture(scope='module')
def cases():
    config = calibrated_config()
    reference = calibrated_config('new ground')
    plain = run_case('effect-free', config, config, seeds=(11,), duration_s=120.0)
    change = run_case('ground change', config, reference, seeds=(11,), duration_s=120.0)
    return plain, change


@pytest.mark.heavy
def test_adapt_recovers_on_a_new_ground_and_fuse_holds_the_heading(cases):
    plain, change = cases
    every = plain.groups['all']
    # fuse's heading: far better than the wheels' (2.3x here, where the exact convention leaves
    # the wheels little heading error; the 3x goal is the Husky's, test_husky.py)
    assert every['fuse'][1].median < every['off'][1].median / 2
    settled = change.groups['on the new ground, settled']
    true_theta = settled['true'][1].median
    assert settled['off'][1].median > 10 * true_theta          # the fixed model is far off
    assert settled['adapt'][1].median <= 1.5 * true_theta      # adapt is within 1.5x
    assert change.recovery_m and max(change.recovery_m) <= 5.0
    # the NEES at 2 m is finite and not over-confident in either gyro mode
    for mode in ('adapt', 'fuse'):
        mean, band, _ = plain.nees[mode]
        assert math.isfinite(mean) and mean <= band[1]


@pytest.mark.heavy
@pytest.mark.xfail(strict=True, reason='known gap (issue 14, open): under the exact midpoint '
                   'convention adapt costs heading on this effect-free drive (0.131 against '
                   '0.105 deg/m); its filter constants are not calibrated per robot')
def test_adapt_costs_nothing_without_a_new_ground(cases):
    plain, _ = cases
    every = plain.groups['all']
    # effect-free: adapt not worse than the fixed model by more than 5 % (heading and position)
    assert every['adapt'][1].median <= 1.05 * every['off'][1].median
    assert every['adapt'][0].median <= 1.05 * every['off'][0].median
