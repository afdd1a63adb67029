"""Exact Jacobians of the augmented rollout against finite differences (C215).

Every extension of the registry, with the base model's parameters free too, on drives with
repeated stamps and a gap: the predictor's forward-mode derivatives of the segment end-pose
errors equal central differences to a relative 1e-6, and the fits that use them land where the
finite-difference fits land.
"""

import numpy as np
import pytest
from skidkin_ros.core.calibration.diagnosis import state as diagnosis_state
from skidkin_ros.core.calibration.diagnosis.options import DiagnosisOptions
from skidkin_ros.core.calibration.engine import ParameterLayout
from skidkin_ros.core.calibration.predictor import SegmentPredictor
from skidkin_ros.core.calibration.segments import cut_segments, SegmentOptions
from skidkin_ros.core.drive import Drive, PoseTrack, WheelSamples
from skidkin_ros.core.kinematics import residual
from skidkin_ros.core.kinematics.extensions import EXTENSION_NAMES, get_extension, LIBRARY
from skidkin_ros.core.kinematics.models import get_model, MODEL_NAMES
from skidkin_ros.core.kinematics.sparse_library import LIBRARY_GRADIENTS
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.integrator import rollout

GEOM = Geometry(0.1651, 0.555)


def _drive(seed, n=260, gap=True):
    """Smooth random wheel speeds (both signs, spins), a repeated stamp, a gap; true poses."""
    rng = np.random.default_rng(seed)
    t_ns = np.cumsum(rng.integers(30_000_000, 70_000_000, n)).astype(np.int64)
    t_ns[n // 4] = t_ns[n // 4 - 1]
    if gap:
        t_ns[n * 5 // 8:] += 1_000_000_000
    phase = rng.uniform(0, 6, 4)
    t = t_ns * 1e-9
    wl = 4 * np.sin(0.3 * t + phase[0]) + 1.5 * np.sin(1.1 * t + phase[1])
    wr = 4 * np.sin(0.25 * t + phase[2]) + 1.5 * np.sin(0.9 * t + phase[3])
    truth_model = get_model('edd_asymmetric').bind(
        {'alpha_l': 0.85, 'alpha_r': 0.9, 'x_v': 0.05, 'y_l': 0.45, 'y_r': -0.4}, GEOM)
    truth = rollout(truth_model.twist(wl[:-1], wr[:-1]), np.diff(t_ns) * 1e-9)
    keep = np.arange(0, n, 2)
    return Drive(f'd{seed}', WheelSamples(t_ns, wl, wr), PoseTrack(t_ns[keep], *truth[keep].T))


@pytest.fixture(scope='module')
def predictor():
    drives = [_drive(1), _drive(2, gap=False)]
    segments = cut_segments(drives, SegmentOptions(horizon_m=1.0))
    return SegmentPredictor(drives, segments)


def _residual_values():
    rng = np.random.default_rng(4)
    values = {name: float(rng.normal(0, 0.02)) for name in residual.coefficient_names()}
    # narrower than the drives: every edge clamps some samples, so every range has a slope
    ranges = {'v_lo': -0.5, 'v_hi': 0.4, 'w_lo': -0.7, 'w_hi': 0.8, 'dv_lo': -0.25,
              'dv_hi': 0.3, 'dw_lo': -0.6, 'dw_hi': 0.5}
    return {**values, **ranges, 'level': 4.0, 'gain_vx': 0.9, 'gain_vy': 1.1, 'gain_wz': 0.8}


# A point inside each extension's range (not its neutral value) and the parameters checked.
POINTS = {
    'time_offset': ({'offset_s': 0.0371}, ('offset_s',)),
    'backlash': ({'play_rad': 0.43}, ('play_rad',)),
    'first_order_lag': ({'tau_s': 0.21}, ('tau_s',)),
    'forward_lag': ({'tau_s': 0.33}, ('tau_s',)),
    'yaw_lag': ({'tau_s': 0.17}, ('tau_s',)),
    'component_lags': ({'tau_v_s': 0.27, 'tau_w_s': 0.12}, ('tau_v_s', 'tau_w_s')),
    'speed_slip': ({'k': 0.3}, ('k',)),
    'direction_asymmetry': ({'k': 0.2, 'blend_m_s': 0.3}, ('k', 'blend_m_s')),
    'lateral_skid': ({'k': 0.07}, ('k',)),
    'icr_offset': ({'x_m': 0.12}, ('x_m',)),
    'ratio_yaw_slip': ({'k': 0.3, 'ratio_peak': 0.4, 'ratio_width': 0.3},
                       ('k', 'ratio_peak', 'ratio_width')),
    'terrain_regime': ({'k': 0.15, 'switch_s': 4.3}, ('k',)),
    'acceleration_slip': ({'tau_s': 0.08}, ('tau_s',)),
    'sparse_correction': ({f'{o}_{t.name}': 0.01 * (i + 1) * (-1) ** i
                           for i, (o, t) in enumerate((o, t) for o in ('vx', 'vy', 'wz')
                                                      for t in LIBRARY)}, None),
    'residual_model': (_residual_values(), None),
}


def _central(predictor, layout, vector, offset):
    columns = []
    for c in range(vector.size):
        # a time offset moves windows by whole nanoseconds: a step of 1 us stays exact
        step = 1e-6 if c == offset else 1e-6 * max(1.0, abs(vector[c]))
        up, down = vector.copy(), vector.copy()
        up[c] += step
        down[c] -= step
        columns.append((predictor.errors(layout.source(up))
                        - predictor.errors(layout.source(down))) / (2 * step))
    return np.stack(columns, axis=-1)


def _check(predictor, layout):
    vector = layout.vector()
    offset = [c for c, (i, j) in enumerate(layout.free)
              if i >= 0 and get_extension(layout.extensions[i]).stage == 'timing']
    offset = offset[0] if offset else None
    exact = predictor.errors_jacobian(layout.source(vector), layout.free, offset)
    numeric = _central(predictor, layout, vector, offset)
    assert np.all(np.isfinite(exact))
    scale = np.abs(numeric).max(axis=(0, 1))
    assert np.all(scale > 0), 'a parameter without effect checks nothing'
    np.testing.assert_allclose(exact, numeric, rtol=1e-6, atol=1e-6 * scale.max())
    # column by column too, so a small column is not hidden by a large one; the floor is the
    # differences' rounding, eps |errors| / step (a bump term few samples reach has a column
    # of 1e-5 and differences off by some 1e-10 at a step of 1e-6, exact at 1e-3)
    for c in range(vector.size):
        assert np.abs(exact[..., c] - numeric[..., c]).max() <= 1e-6 * scale[c] + 1e-9


def test_every_extension_is_covered():
    assert set(POINTS) == set(EXTENSION_NAMES)
    assert set(LIBRARY_GRADIENTS) == {term.name for term in LIBRARY}
    assert set(residual.TERM_GRADIENTS) == set(residual.term_names())


@pytest.mark.parametrize('name', EXTENSION_NAMES)
def test_extension_jacobian_equals_central_differences(predictor, name):
    values, params = POINTS[name]
    ext = get_extension(name)
    if params is None:  # learned: every coefficient, and the residual model's gains and ranges
        params = tuple(p for p in ext.param_names if p != 'level')
    base = {'alpha': 0.93, 'b_hat': 0.71}
    for refit_base in (True, False):  # with a tangent carried in, and without
        layout = ParameterLayout.build('edd_symmetric', GEOM, base, {name: values}, (name,),
                                       refit_base, {name: params})
        _check(predictor, layout)


@pytest.mark.parametrize('model', [m for m in MODEL_NAMES if m != 'ideal_dd'])
def test_base_model_jacobians(predictor, model):
    values = {'edd_symmetric': {'alpha': 0.93, 'b_hat': 0.71},
              'edd_asymmetric': {'alpha_l': 0.9, 'alpha_r': 0.8, 'x_v': 0.04, 'y_l': 0.4,
                                 'y_r': -0.35},
              'roc': {'alpha': 0.9, 'beta_1': 0.6, 'beta_2': 0.4},
              'full_linear': {}}[model]
    plain = ParameterLayout.build(model, GEOM, values, {}, (), True, {})
    _check(predictor, plain)
    chained = ParameterLayout.build(model, GEOM, values,
                                    {'lateral_skid': {'k': 0.05},
                                     'first_order_lag': {'tau_s': 0.15}},
                                    ('lateral_skid', 'first_order_lag'), True,
                                    {'lateral_skid': ('k',), 'first_order_lag': ('tau_s',)})
    _check(predictor, chained)


def test_a_chain_of_extensions_with_an_offset(predictor):
    names = ('time_offset', 'backlash', 'speed_slip', 'icr_offset', 'acceleration_slip',
             'residual_model', 'component_lags')
    values = {n: POINTS[n][0] for n in names}
    free = {n: POINTS[n][1] or ('gain_vx', 'gain_vy', 'gain_wz') for n in names}
    layout = ParameterLayout.build('edd_symmetric', GEOM, {'alpha': 0.93, 'b_hat': 0.71},
                                   values, names, True, free)
    _check(predictor, layout)


def test_a_lag_at_zero_takes_its_one_sided_slope(predictor):
    layout = ParameterLayout.build('edd_symmetric', GEOM, {}, {'yaw_lag': {'tau_s': 0.0}},
                                   ('yaw_lag',), False, {'yaw_lag': ('tau_s',)})
    exact = predictor.errors_jacobian(layout.source(layout.vector()), layout.free)
    step = 1e-7
    numeric = (predictor.errors(layout.source(np.array([step])))
               - predictor.errors(layout.source(np.array([0.0])))) / step
    np.testing.assert_allclose(exact[..., 0], numeric, rtol=1e-4,
                               atol=1e-4 * np.abs(numeric).max())


def test_fits_with_the_exact_jacobian_land_where_finite_differences_do(predictor, monkeypatch):
    """The same optimum (to the fits' tolerance) with both Jacobians, base refitted too."""
    start = diagnosis_state.ModelState(
        ('time_offset', 'lateral_skid', 'first_order_lag'), {'alpha': 1.0, 'b_hat': 0.6},
        {'time_offset': {'offset_s': 0.01}, 'lateral_skid': {'k': 0.0},
         'first_order_lag': {'tau_s': 0.1}},
        found=('time_offset', 'lateral_skid', 'first_order_lag'))
    options = DiagnosisOptions()
    fitted = {}
    for exact in (True, False):
        monkeypatch.setattr(diagnosis_state, 'ANALYTIC_JACOBIAN', exact)
        fitted[exact] = diagnosis_state.fit_state(predictor, 'edd_symmetric', GEOM, start,
                                                  options)
    (exact_state, exact_cost), (fd_state, fd_cost) = fitted[True], fitted[False]
    assert exact_cost == pytest.approx(fd_cost, rel=1e-6)
    assert exact_cost < 0.5 * diagnosis_state.fit_state(
        predictor, 'edd_symmetric', GEOM, start, options, refit_base=False,
        fixed=('time_offset.offset_s', 'lateral_skid.k', 'first_order_lag.tau_s'))[1]
    for name, value in exact_state.base_values.items():
        assert value == pytest.approx(fd_state.base_values[name], rel=1e-4, abs=1e-6)
    for ext, values in exact_state.ext_values.items():
        for name, value in values.items():
            assert value == pytest.approx(fd_state.ext_values[ext][name], rel=1e-3, abs=1e-5)


def test_the_backlash_on_a_base_not_linear_in_the_wheel_speeds(predictor):
    """The play's slope goes through ROC's twist, which is not linear in the wheel speeds."""
    layout = ParameterLayout.build('roc', GEOM, {'alpha': 0.9, 'beta_1': 0.6, 'beta_2': 0.4},
                                   {'backlash': {'play_rad': 0.43}}, ('backlash',), True,
                                   {'backlash': ('play_rad',)})
    _check(predictor, layout)
