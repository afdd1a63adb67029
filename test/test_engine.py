"""The one least-squares engine: layouts from the specs, one penalty, both fits agree."""

import math

from _calib_synth import GEOMETRY, make_drive
import numpy as np
import pytest

from skidkin_ros.core.calibration.diagnosis import DiagnosisOptions, ModelState
from skidkin_ros.core.calibration.diagnosis.state import fit_state
from skidkin_ros.core.calibration.engine import (NONFINITE_PENALTY, ParameterLayout,
                                                 segment_losses, solve, whitened_residuals)
from skidkin_ros.core.calibration.fitting import fit_model, FitOptions
from skidkin_ros.core.calibration.predictor import SegmentPredictor
from skidkin_ros.core.calibration.segments import cut_segments, SegmentOptions
from skidkin_ros.core.kinematics.augmented import BoundAugmented

SEGMENTS = SegmentOptions(horizon_m=2.0, horizon_rad=1.0)


def _drive(seed=3, duration_s=120.0):
    return make_drive('edd_symmetric', duration_s=duration_s, rate_hz=20.0, truth_every=2,
                      seed=seed, wheel_noise=0.02, truth_noise_m=0.005, truth_noise_rad=0.002)


def test_layout_takes_bounds_from_the_specs_and_fixes_what_is_not_free():
    layout = ParameterLayout.build('edd_symmetric', GEOMETRY, {'alpha': 0.9},
                                   {'ratio_yaw_slip': {'k': 0.2}}, ('ratio_yaw_slip',), True,
                                   {'ratio_yaw_slip': ('k', 'ratio_width')})
    lo, hi = layout.bounds()
    # alpha [0, 1], b_hat (0, inf) pulled in by 1e-6, k [-0.9, 0.95], ratio_width (0, 1]
    assert lo.tolist() == [0.0, 1e-6, -0.9, 1e-6]
    assert hi.tolist() == [1.0, math.inf, 0.95, 1.0]
    np.testing.assert_array_equal(layout.vector(), [0.9, GEOMETRY.track_width, 0.2, 0.15])
    base, ext = layout.values(np.array([0.8, 0.7, 0.3, 0.2]))
    assert base == {'alpha': 0.8, 'b_hat': 0.7}
    assert ext == {'ratio_yaw_slip': {'k': 0.3, 'ratio_peak': 0.5, 'ratio_width': 0.2}}
    source = layout.source(np.array([0.8, 0.7, 0.3, 0.2]))
    assert isinstance(source, BoundAugmented) and source.base.values == base
    plain = ParameterLayout.of_model('full_linear', GEOMETRY)
    assert len(plain.free) == 6 and plain.source(plain.vector()).name == 'full_linear'


def test_a_non_finite_prediction_becomes_the_penalty_not_a_failure():
    errors = np.array([[0.1, np.nan, -np.inf], [0.2, 0.0, np.inf]])
    residuals = whitened_residuals(errors, np.array([1.0, 2.0, 1.0]))
    assert residuals.tolist() == [0.1, NONFINITE_PENALTY, -NONFINITE_PENALTY, 0.2, 0.0,
                                  NONFINITE_PENALTY]
    assert segment_losses(errors, np.ones(3)).tolist() == [NONFINITE_PENALTY] * 2
    # a fit whose every prediction is NaN ends on the penalty instead of raising
    layout = ParameterLayout.of_model('edd_symmetric', GEOMETRY)
    sol = solve(lambda source: np.full((4, 3), np.nan), layout, np.ones(3), max_nfev=2)
    assert sol.cost == pytest.approx(0.5 * 12 * NONFINITE_PENALTY ** 2)


def test_the_calibration_fit_and_the_diagnosis_fit_agree_on_a_plain_model():
    """Both run the same engine; only how a segment is predicted differs (to rounding)."""
    drive = _drive()
    segments = cut_segments([drive], SEGMENTS)
    calibrated = fit_model('edd_symmetric', GEOMETRY, segments,
                           FitOptions(trim=False, n_starts=1))
    diagnosed, cost = fit_state(SegmentPredictor([drive], segments), 'edd_symmetric', GEOMETRY,
                                ModelState((), {}, {}), DiagnosisOptions(max_nfev=60))
    for name, value in calibrated.values.items():
        assert diagnosed.base_values[name] == pytest.approx(value, rel=1e-5), name
    assert cost == pytest.approx(calibrated.cost, rel=1e-6)
    assert calibrated.values['alpha'] == pytest.approx(0.9, abs=0.01)
