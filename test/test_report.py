"""The calibration recipe end to end: report page, figures and the parameters file."""

from _calib_synth import GEOMETRY, make_drive
import pytest

from skidkin_ros.core.calibration.pipeline import (calibrate, CalibrationOptions, horizon_study,
                                                   result_to_parameters)
from skidkin_ros.core.odometry.config import OdometryConfig, read_params_file, write_params_file
from skidkin_ros.errors import FitError, OutputError
from skidkin_ros.report import write_report

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'


@pytest.fixture(scope='module')
def result():
    train = [make_drive('edd_symmetric', duration_s=240.0, rate_hz=20.0, truth_every=2, seed=1,
                        wheel_noise=0.05, truth_noise_m=0.005, truth_noise_rad=0.003)]
    evaluate = [make_drive('edd_symmetric', duration_s=160.0, rate_hz=20.0, truth_every=2,
                           seed=2, wheel_noise=0.05, truth_noise_m=0.005,
                           truth_noise_rad=0.003)]
    return calibrate(train, evaluate, GEOMETRY, CalibrationOptions(seed=1))


def test_calibration_result(result):
    assert set(result.fits) == {'ideal_dd', 'edd_symmetric', 'edd_asymmetric', 'roc',
                                'full_linear'}
    assert result.fits['edd_symmetric'].values['b_hat'] == pytest.approx(1.04, rel=0.02)
    assert result.best != 'ideal_dd'
    ideal = result.evaluation['ideal_dd'].stats_t.median
    assert result.evaluation[result.best].stats_t.median < 0.3 * ideal
    assert result.counts['train']['kept'] == len(result.train_segments)
    assert set(result.noise) == set(result.fits)


def test_report_page_and_figures(result, tmp_path):
    study = horizon_study(
        [make_drive('edd_symmetric', duration_s=120.0, rate_hz=20.0, truth_every=2, seed=3)],
        [make_drive('edd_symmetric', duration_s=80.0, rate_hz=20.0, truth_every=2, seed=4)],
        GEOMETRY, CalibrationOptions(models=('edd_symmetric',)), [1.0, 2.0], [1.0, 2.0])
    page = write_report(result, tmp_path / 'out', study=study)
    text = page.read_text()
    assert f'**Best model: `{result.best}`**' in text
    assert '| `edd_symmetric` | b_hat |' in text and 'b_hat / b =' in text
    assert 'inside 95 % (3 dof)' in text and '## Provenance' in text
    for name in ('errors.png', 'rotation_per_metre.png', 'angular_error_map.png',
                 'segment_paths.png', 'horizons.png'):
        assert f']({name})' in text
        assert (tmp_path / 'out' / name).read_bytes()[:8] == PNG_MAGIC
    with pytest.raises(OutputError, match='already exists'):
        write_report(result, tmp_path / 'out')
    assert write_report(result, tmp_path / 'out', force=True) == page


def test_segment_figure_draws_each_model_beside_the_true_path_on_one_scale(result):
    import matplotlib.pyplot as plt
    import numpy as np
    from skidkin_ros.report.figures import segment_paths_figure
    fig = segment_paths_figure(result, count=4)
    axes = fig.axes
    assert len(axes) == 4
    spans = set()
    for ax in axes:
        lines = {line.get_label(): line for line in ax.get_lines()}
        assert set(result.fits) <= set(lines)
        truth = lines['ground truth'].get_xydata()
        assert len(truth) > 5  # the whole true path, not only its end point
        start = ax.get_lines()[-2].get_xydata()[0]  # the start marker
        assert np.allclose(truth[0], start, atol=1e-9)
        for name in result.fits:  # every model starts at the true start pose
            assert np.allclose(lines[name].get_xydata()[0], start)
        assert ax.get_aspect() == 1.0
        spans.add((round(np.diff(ax.get_xlim())[0], 9), round(np.diff(ax.get_ylim())[0], 9)))
    assert len(spans) == 1  # the same scale in every panel
    plt.close(fig)


def test_the_report_shows_no_fault_matrix_codes(result, tmp_path):
    import re
    text = write_report(result, tmp_path / 'codes').read_text()
    assert re.findall(r'\([CN][0-9]+\)', text) == []


def test_parameters_file_round_trip(result, tmp_path):
    flat = result_to_parameters(result, {'robot': 'synth'})
    assert flat['model'] == result.best
    assert flat['models.edd_symmetric.b_hat'] == result.fits['edd_symmetric'].values['b_hat']
    assert flat['models.edd_symmetric.noise.calibrated'] is True
    path = write_params_file(tmp_path / 'params.yaml', flat, result.provenance)
    config = OdometryConfig.from_flat(read_params_file(path))
    assert config.model == result.best and config.noise['edd_symmetric'] is not None
    assert config.model_values['edd_symmetric']['alpha'] == pytest.approx(
        result.fits['edd_symmetric'].values['alpha'])


def test_unobservable_parameters_are_not_written():
    """C14: straight driving only: no model can be calibrated, the writer refuses and says why."""
    drives = [make_drive('edd_symmetric', kind='straight', duration_s=120.0, rate_hz=20.0,
                         truth_every=2, seed=s) for s in (1, 2)]
    result = calibrate(drives[:1], drives[1:], GEOMETRY, CalibrationOptions())
    assert result.best == 'ideal_dd'
    with pytest.raises(FitError, match='b_hat'):
        result_to_parameters(result, {})
    flat = result_to_parameters(result, {}, allow_invalid=True)
    assert 'models.edd_symmetric.b_hat' in flat
