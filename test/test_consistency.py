"""NEES machinery, odometry NEES over independent windows, and the end-to-end estimation study."""

from _calib_synth import GEOMETRY, make_drive
from lab.report.estimation import write_estimation_figures
from lab.studies.estimation import run_estimation_study, StudyOptions
import numpy as np
import pytest
from scipy import stats

from skidkin_ros.core.calibration.noise_fit import segment_covariances, segment_motion
from skidkin_ros.core.calibration.segments import cut_segments, SegmentOptions
from skidkin_ros.core.estimation.nees import (chi2_band, nees, nees_over_time, segment_nees,
                                              summarize_nees)
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.odometry.noise import NoiseModel
from skidkin_ros.errors import DataError

NOISE = NoiseModel(4e-3, 1e-3, 2e-4, 5e-3)


def _random_covariances(rng, n, dof):
    root = rng.normal(size=(n, dof, dof))
    return root @ np.swapaxes(root, 1, 2) + 0.1 * np.eye(dof)


def test_nees_of_a_known_gaussian_is_chi2_and_wrong_covariances_are_flagged():
    rng = np.random.default_rng(0)
    covs = _random_covariances(rng, 4000, 3)
    errors = np.einsum('nij,nj->ni', np.linalg.cholesky(covs), rng.normal(size=(4000, 3)))
    values = nees(errors, covs)
    # the distribution, not only the mean: a KS test against chi2(3)
    assert stats.kstest(values, 'chi2', args=(3,)).pvalue > 0.01
    right = summarize_nees(values[:300], 3)
    assert right.consistent and right.verdict() == 'consistent'
    assert 0.92 <= summarize_nees(values, 3).inside_95 <= 0.98
    too_small = summarize_nees(nees(errors[:300], covs[:300] / 2.0), 3)
    too_large = summarize_nees(nees(errors[:300], covs[:300] * 2.0), 3)
    assert too_small.verdict() == 'over-confident'
    assert too_large.verdict() == 'conservative'


def test_chi2_band_covers_95_percent_of_simulated_averages():
    rng = np.random.default_rng(1)
    count, dof = 20, 3
    averages = rng.chisquare(dof, size=(20000, count)).mean(axis=1)
    low, high = chi2_band(count, dof)
    inside = np.mean((averages >= low) & (averages <= high))
    assert inside == pytest.approx(0.95, abs=0.01)
    assert chi2_band(1, 2) == pytest.approx(tuple(stats.chi2.ppf([0.025, 0.975], 2)))
    assert np.diff(chi2_band(1000, 3))[0] < np.diff(chi2_band(10, 3))[0]
    with pytest.raises(DataError):
        chi2_band(0, 3)


def test_nees_over_time_averages_the_runs_against_the_band_for_m_runs():
    rng = np.random.default_rng(2)
    runs, steps = 10, 500
    covs = np.broadcast_to(np.diag([0.04, 0.01, 0.001]), (runs, steps, 3, 3))
    errors = rng.normal(size=(runs, steps, 3)) * np.sqrt([0.04, 0.01, 0.001])
    result = nees_over_time(np.arange(steps) * 0.05, errors, covs)
    assert result.mean.shape == (steps,)
    assert result.band == pytest.approx(chi2_band(runs, 3))
    assert result.share_inside == pytest.approx(0.95, abs=0.03)
    assert result.time_average == pytest.approx(3.0, abs=0.1)
    shrunk = nees_over_time(result.t_s, errors, covs / 3.0)
    assert shrunk.share_inside < 0.5


def test_segment_nees_uses_the_propagated_covariance_of_the_calibrated_noise():
    """The windows' covariance is propagation.predict's, and equals the calibrator's basis."""
    drive = make_drive('edd_symmetric', duration_s=200.0, rate_hz=20.0, truth_every=1, seed=4)
    values = {'alpha': 0.9, 'b_hat': 1.04}
    source = get_model('edd_symmetric').bind(values, GEOMETRY)
    options = SegmentOptions(horizon_m=2.0, short_drive='drop')
    result = segment_nees([drive], source, NOISE, options)
    segments = cut_segments([drive], options)
    assert len(result.nees) == len(segments) > 20
    expected = segment_covariances(NOISE, segment_motion('edd_symmetric', values, GEOMETRY,
                                                         segments))
    np.testing.assert_allclose(result.covs, expected, rtol=1e-9, atol=1e-14)
    # the synthetic drive is noise-free and exact: the odometry errors vanish
    assert np.abs(result.errors).max() < 1e-6
    assert result.summary().verdict() == 'conservative'


def test_segment_nees_on_drives_too_short_is_refused():
    drive = make_drive('edd_symmetric', duration_s=2.0, rate_hz=20.0, truth_every=1, seed=4)
    source = get_model('ideal_dd').bind({}, GEOMETRY)
    with pytest.raises(DataError, match='no window'):
        segment_nees([drive], source, NOISE, SegmentOptions(horizon_m=50.0, short_drive='drop'))


@pytest.mark.heavy
def test_estimation_study_odometry_and_filter_are_consistent_and_the_filter_wins(tmp_path):
    options = StudyOptions(train_s=240.0, calib_drives=4, test_drives=4, test_s=150.0,
                           other_horizons_m=(), models=('edd_asymmetric',), n_starts=1,
                           fix_sweep=((0.1, None),))
    study = run_estimation_study(seed=0, options=options)
    # the sensitivity runs hold the wheel speeds as the calibration did: odometry alone (which
    # no fix touches) is the same in every run
    np.testing.assert_array_equal(study.sweep[(0.1, None)].odom_errors, study.runs.odom_errors)
    odometry = study.odometry_summary
    assert odometry.count > 60
    assert odometry.band[0] <= odometry.mean <= odometry.band[1], study.summary_lines()
    ekf = study.filter_summary
    assert ekf.band[0] <= ekf.mean <= ekf.band[1], study.summary_lines()
    assert study.runs.ekf_nees_over_time().share_inside >= 0.85
    ekf_position, ekf_yaw = study.runs.ekf_rmse()
    odom_position, odom_yaw = study.runs.odom_rmse()
    assert ekf_position < 0.5 * odom_position
    assert ekf_yaw < odom_yaw
    whole = study.whole  # whole drives from the start: one value per drive and distance
    assert whole.nees.shape[0] == 4 and whole.distances_m[0] == 1.0
    assert whole.distances_m[-1] == pytest.approx(whole.drive_length_m.min())
    assert np.all(np.isfinite(whole.nees)) and whole.checkpoint_nees.size == 4 * 10
    figures = write_estimation_figures(tmp_path / 'figures', study)
    assert len(figures) == 4
    for path in figures.values():
        assert path.exists() and path.stat().st_size > 10_000
    lines = study.summary_lines()
    assert any('average NEES' in line for line in lines)
