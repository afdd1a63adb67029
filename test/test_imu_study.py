"""The gyro study on the simulator (the gyro's goals), sized down: one ground-change drive.

The effect-free case runs the three drives of docs/results.md (50 segments of 2 m): one drive's 16
segments cannot resolve the 5 % of the effect-free goal (the fixed model's median eps_t of seed
11 alone is 27 % below that of the three). The study calibrates and scores under
``interval: midpoint`` (exact for the simulator's speeds).
"""

from lab.studies.imu import calibrated_config, run_case
import pytest


@pytest.fixture(scope='module')
def cases():
    config = calibrated_config()
    reference = calibrated_config('new ground')
    plain = run_case('effect-free', config, config, seeds=(11, 12, 13), duration_s=120.0)
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
    # the NEES at 2 m is inside the 95 % band in every mode: the gyro modes' noise (imu.arw,
    # imu.adapt.r_floor / r_rel / yaw_noise_scale) is calibrated on this robot's drives
    for mode in ('off', 'adapt', 'fuse'):
        mean, band, _ = plain.nees[mode]
        assert band[0] <= mean <= band[1], (mode, mean, band)


@pytest.mark.heavy
def test_adapt_costs_nothing_without_a_new_ground(cases):
    plain, _ = cases
    every = plain.groups['all']
    # effect-free: adapt not worse than the fixed model by more than 5 % (heading and position)
    assert every['adapt'][1].median <= 1.05 * every['off'][1].median
    assert every['adapt'][0].median <= 1.05 * every['off'][0].median
