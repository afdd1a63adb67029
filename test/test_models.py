"""Closed-form checks of the five kinematic models and their registry."""

import math

import numpy as np
import pytest
from skidkin_ros.core.kinematics.models import get_model, MODEL_NAMES, MODELS, RocModel
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.errors import ParameterError

GEOM = Geometry(wheel_radius=0.3, track_width=1.2)


def twist(name, values, wl, wr, geometry=GEOM):
    return get_model(name).bind(values, geometry).twist(np.asarray(wl, float),
                                                        np.asarray(wr, float))


def test_registry_has_the_five_public_names():
    assert MODEL_NAMES == ('ideal_dd', 'edd_symmetric', 'edd_asymmetric', 'roc', 'full_linear')
    for name in MODEL_NAMES:
        assert get_model(name) is MODELS[name]


def test_unknown_model_lists_the_known_ones():
    with pytest.raises(ParameterError) as err:
        get_model('ackermann')
    for name in MODEL_NAMES:
        assert name in str(err.value)


def test_public_parameter_names_are_stable():
    names = {name: get_model(name).param_names for name in MODEL_NAMES}
    assert names == {
        'ideal_dd': (),
        'edd_symmetric': ('alpha', 'b_hat'),
        'edd_asymmetric': ('alpha_l', 'alpha_r', 'x_v', 'y_l', 'y_r'),
        'roc': ('alpha', 'beta_1', 'beta_2'),
        'full_linear': ('gamma_11', 'gamma_12', 'gamma_21', 'gamma_22', 'gamma_31', 'gamma_32'),
    }


@pytest.mark.parametrize('name', MODEL_NAMES)
def test_defaults_are_the_ideal_differential_drive(name):
    rng = np.random.default_rng(3)
    wl, wr = rng.uniform(-8, 8, (2, 50))
    np.testing.assert_allclose(twist(name, {}, wl, wr), twist('ideal_dd', {}, wl, wr),
                               rtol=1e-12, atol=1e-12)


def test_ideal_straight_line_and_spin():
    # straight: v = r w, no rotation; spin: v = 0, omega = 2 r w / b
    np.testing.assert_allclose(twist('ideal_dd', {}, [2.0], [2.0])[0], [0.6, 0.0, 0.0])
    np.testing.assert_allclose(twist('ideal_dd', {}, [-2.0], [2.0])[0], [0.0, 0.0, 1.0])


def test_edd_symmetric_formula():
    out = twist('edd_symmetric', {'alpha': 0.8, 'b_hat': 2.0}, [1.0], [3.0])[0]
    r, alpha, b_hat = 0.3, 0.8, 2.0
    np.testing.assert_allclose(out, [r * alpha * 2.0, 0.0, r * alpha * 2.0 / b_hat])


def test_symmetric_equals_asymmetric_with_symmetric_parameters():
    rng = np.random.default_rng(0)
    wl, wr = rng.uniform(-6, 6, (2, 100))
    sym = twist('edd_symmetric', {'alpha': 0.87, 'b_hat': 3.1}, wl, wr)
    asym = twist('edd_asymmetric', {'alpha_l': 0.87, 'alpha_r': 0.87, 'x_v': 0.0,
                                    'y_l': 1.55, 'y_r': -1.55}, wl, wr)
    np.testing.assert_allclose(sym, asym, rtol=1e-12, atol=1e-14)


def test_edd_asymmetric_lateral_velocity_from_x_v():
    values = {'alpha_l': 1.0, 'alpha_r': 1.0, 'x_v': -0.5, 'y_l': 0.6, 'y_r': -0.6}
    out = twist('edd_asymmetric', values, [-1.0], [1.0])[0]
    # pure spin about an ICR at x_v behind the centre: v_y = -x_v * omega
    omega = 0.3 * 2 / 1.2
    np.testing.assert_allclose(out, [0.0, 0.5 * omega, omega])


def test_edd_asymmetric_rejects_crossed_icrs():
    # the ranges already keep y_l > 0 > y_r; the cross-check guards any other route in
    with pytest.raises(ParameterError, match='y_l .* must be greater than y_r'):
        get_model('edd_asymmetric').check_constraints(np.array([1.0, 1.0, 0.0, 0.1, 0.2]))


def test_full_linear_is_its_matrix():
    gammas = {'gamma_11': 0.1, 'gamma_12': 0.2, 'gamma_21': -0.3, 'gamma_22': 0.4,
              'gamma_31': -0.5, 'gamma_32': 0.6}
    out = twist('full_linear', gammas, [2.0], [3.0])[0]
    np.testing.assert_allclose(out, [0.1 * 2 + 0.2 * 3, -0.3 * 2 + 0.4 * 3, -0.5 * 2 + 0.6 * 3])


def test_roc_formula_on_a_constant_arc():
    k = {'alpha': 0.9, 'beta_1': 1.5, 'beta_2': 0.7}
    wl, wr = 1.0, 3.0
    lam = abs((wr + wl) / (wr - wl))
    y0 = 1.2 / 2 * (1 + 1.5 / (1 + 0.7 * math.sqrt(lam)))
    expected = [0.3 * 0.9 * (wl + wr) / 2, 0.0, 0.3 * 0.9 * (wr - wl) / (2 * y0)]
    np.testing.assert_allclose(twist('roc', k, [wl], [wr])[0], expected, rtol=1e-12)


@pytest.mark.parametrize('beta', [(1.36, -0.18), (42.73, 11.09), (0.0, 0.0), (-0.5, 0.0),
                                  (2.0, -1.0)])
def test_roc_finite_at_straight_spin_standstill_and_singularity(beta):
    k = {'alpha': 0.8, 'beta_1': beta[0], 'beta_2': beta[1]}
    wl = np.array([2.0, -2.0, 0.0, 1.0, 3.0, -3.0, 1.0])
    wr = np.array([2.0, 2.0, 0.0, 1.0 + 1e-12, 1.0, -1.0, 9.0])
    out = twist('roc', k, wl, wr)
    assert np.all(np.isfinite(out))
    # straight driving never turns; standstill never moves
    assert out[0, 2] == 0.0 and np.all(out[2] == 0.0)


def test_roc_straight_limit_is_continuous():
    k = np.array([0.9, 1.36, 0.5])
    model = RocModel()
    straight = model.icr_distance(k, GEOM, np.array([2.0]), np.array([2.0]))
    near = model.icr_distance(k, GEOM, np.array([2.0]), np.array([2.0 + 1e-10]))
    np.testing.assert_allclose(near, straight, rtol=1e-4)


@pytest.mark.parametrize('name', MODEL_NAMES)
def test_vectorized_over_any_shape(name):
    wl = np.linspace(-3, 3, 24).reshape(2, 3, 4)
    wr = wl[::-1] * 0.5 + 0.1
    out = twist(name, {}, wl, wr)
    assert out.shape == (2, 3, 4, 3)
    np.testing.assert_allclose(out[1, 2, 3], twist(name, {}, [wl[1, 2, 3]], [wr[1, 2, 3]])[0])


@pytest.mark.parametrize('name,param,bad', [
    ('edd_symmetric', 'alpha', 1.5), ('edd_symmetric', 'b_hat', 0.0),
    ('edd_symmetric', 'b_hat', float('nan')), ('edd_asymmetric', 'y_l', -0.1),
    ('edd_asymmetric', 'y_r', 0.2), ('roc', 'alpha', -0.1), ('full_linear', 'gamma_31', 0.1),
    ('edd_symmetric', 'alpha', '0.9'),
])
def test_out_of_range_values_name_the_parameter_and_range(name, param, bad):
    with pytest.raises(ParameterError) as err:
        get_model(name).vector({param: bad}, GEOM)
    assert f'models.{name}.{param}' in str(err.value)


def test_unknown_parameter_is_rejected():
    with pytest.raises(ParameterError, match='no parameter'):
        get_model('roc').vector({'gamma_11': 1.0}, GEOM)


def test_geometry_rejects_nonpositive_radius():
    with pytest.raises(ParameterError, match='wheel_radius'):
        Geometry(0.0, 0.5)


SCALAR_CASES = {
    'ideal_dd': {},
    'edd_symmetric': {'alpha': 0.9, 'b_hat': 1.7},
    'edd_asymmetric': {'alpha_l': 0.9, 'alpha_r': 0.8, 'x_v': -0.2, 'y_l': 0.8, 'y_r': -0.7},
    'roc': {'alpha': 0.85, 'beta_1': 1.3, 'beta_2': 0.4},
    'full_linear': {'gamma_11': 0.14, 'gamma_12': 0.16, 'gamma_21': 0.01, 'gamma_22': -0.02,
                    'gamma_31': -0.2, 'gamma_32': 0.21},
}


@pytest.mark.parametrize('name', MODEL_NAMES)
def test_scalar_twist_is_the_vectorized_twist_bit_for_bit(name):
    """The node's plain-float path must give exactly what fitting and predict compute."""
    bound = get_model(name).bind(SCALAR_CASES[name], GEOM)
    rng = np.random.default_rng(5)
    pairs = [(0.0, 0.0), (2.0, 2.0), (-2.0, 2.0), (3.0, -3.0), (-1.5, -1.5), (0.0, 4.0)]
    pairs += [tuple(p) for p in rng.uniform(-10, 10, (200, 2))]
    for wl, wr in pairs:
        assert bound.scalar_twist(wl, wr) == tuple(bound.twist(wl, wr).tolist()), (wl, wr)


@pytest.mark.parametrize('beta', [(0.0, 0.0), (1.0, 0.0), (-0.4, 0.0), (1.0, -1.0), (-0.5, -2.0),
                                  (2.0, 3.0)])
def test_roc_scalar_icr_distance_matches_at_singular_points(beta):
    k = np.array([1.0, *beta])
    for wl, wr in [(0.0, 0.0), (1.0, 1.0), (-1.0, 1.0), (1.0, -1.0), (2.0, 1.0), (0.5, 3.0)]:
        vector = float(RocModel.icr_distance(k, GEOM, np.array(wl), np.array(wr)))
        assert RocModel.icr_distance_scalar(k, GEOM, wl, wr) == vector, (beta, wl, wr)
