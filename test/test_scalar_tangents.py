"""The exact float d twist / dk per sample: the array forward mode's, central differences'."""

import numpy as np
import pytest
from skidkin_ros.core.calibration.engine import ParameterLayout
from skidkin_ros.core.kinematics import residual
from skidkin_ros.core.kinematics.extensions import get_extension, SLIP_LEVER_M
from skidkin_ros.core.kinematics.scalar_tangents import SCALAR_PARTIALS, scalar_tangents
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.online.augmented import LayoutModel, LayoutUncertainty, online_layout

GEOMETRY = Geometry(0.165, 0.555)
BASE = {'alpha_l': 0.93, 'alpha_r': 0.88, 'x_v': 0.04, 'y_l': 0.41, 'y_r': -0.37}
# values of each extension (random draws below scale around them), and the speed range
EXTENSIONS = {
    'speed_slip': {'k': 0.12},
    'direction_asymmetry': {'k': 0.2, 'blend_m_s': 0.4},
    'lateral_skid': {'k': 0.03},
    'icr_offset': {'x_m': 0.05},
    'ratio_yaw_slip': {'k': 0.2, 'ratio_peak': 0.4, 'ratio_width': 0.3},
    'acceleration_slip': {'tau_s': 0.05},
}


def _residual_values(rng: np.random.Generator, clip: bool) -> dict[str, float]:
    """Return a residual model with every library term in use (random coefficients, ranges)."""
    names = residual.coefficient_names()
    scale = 3.0 if clip else 0.05   # clip: corrections beyond the bound on some samples
    values = {name: float(v) for name, v in zip(names, rng.normal(0.0, scale, len(names)))}
    edges = ((-2.0, 2.5), (-1.5, 1.2), (-3.0, 2.0), (-2.5, 3.5))
    for (name, _, _), (lo, hi) in zip(residual.INPUTS, edges):
        values[f'{name}_lo'], values[f'{name}_hi'] = lo, hi
    values['level'] = 7.0
    values.update(gain_vx=1.2, gain_vy=0.8, gain_wz=1.05)
    return values


def _layout_model(extensions, rng, clip=False) -> LayoutModel:
    ext_values = {}
    for name in extensions:
        if name == 'residual_model':
            ext_values[name] = _residual_values(rng, clip)
        else:
            ext = get_extension(name)
            given = EXTENSIONS[name]
            ext_values[name] = {p: given[p] * float(rng.uniform(0.8, 1.2))
                                for p in ext.param_names}
    base = {k: v * float(rng.uniform(0.95, 1.05)) for k, v in BASE.items()}
    # every parameter free (more than online learns), the residual model's gains only
    free = {name: get_extension(name).param_names if name != 'residual_model'
            else get_extension(name).fitted for name in extensions}
    return LayoutModel(ParameterLayout.build('edd_asymmetric', GEOMETRY, base, ext_values,
                                             tuple(extensions), True, free))


def _central(model: LayoutModel, k: np.ndarray, left, right, rate_l, rate_r) -> np.ndarray:
    """Return d twist / dk by central differences of the float twist (the form replaced)."""
    out = []
    for j in range(k.size):
        step = 1e-6 * max(abs(float(k[j])), 1.0)
        sides = []
        for sign in (1.0, -1.0):
            kk = k.copy()
            kk[j] += sign * step
            bound = model.source(kk)
            sides.append(np.array(bound.scalar_memoryless(
                left, right, 0.0, bound.base.scalar_twist(rate_l, rate_r),
                bound.base.scalar_twist(left, right))))
        out.append((sides[0] - sides[1]) / (2.0 * step))
    return np.array(out).T   # (3, p)


def _exact_arrays(model: LayoutModel, k: np.ndarray, left, right, rate_l, rate_r) -> np.ndarray:
    """Return the array forward mode (Extension.partials): the fits' own exact Jacobian."""
    if model.paired:
        return model.twist_gradient(k, GEOMETRY, np.array([[left - rate_l, left]]),
                                    np.array([[right - rate_r, right]]))[0, 1]
    return model.twist_gradient(k, GEOMETRY, left, right)


CASES = [(name,) for name in EXTENSIONS] + [
    ('speed_slip', 'lateral_skid', 'ratio_yaw_slip'),
    ('direction_asymmetry', 'icr_offset', 'acceleration_slip'),
    ('residual_model',), ('speed_slip', 'residual_model'),
    ('lateral_skid', 'acceleration_slip', 'residual_model')]


@pytest.mark.parametrize('extensions', CASES, ids=['+'.join(c) for c in CASES])
def test_float_tangents_equal_the_array_forward_mode_and_central_differences(extensions):
    rng = np.random.default_rng(len(extensions) * 7 + len(extensions[0]))
    for clip in (False, True) if 'residual_model' in extensions else (False,):
        model = _layout_model(extensions, rng, clip)
        k = model.layout.vector()
        tangents = scalar_tangents(model.source(k), model.layout.free)
        assert tangents is not None
        worst_exact = worst_central = 0.0
        for left, right, rate_l, rate_r in rng.uniform(-12.0, 12.0, (60, 4)):
            if not model.paired:
                rate_l = rate_r = 0.0
            floats = np.array(tangents.jacobian(left, right, rate_l, rate_r)).T
            exact = _exact_arrays(model, k, left, right, rate_l, rate_r)
            central = _central(model, k, left, right, rate_l, rate_r)
            scale = max(np.abs(exact).max(), 1e-300)
            worst_exact = max(worst_exact, np.abs(floats - exact).max() / scale)
            worst_central = max(worst_central, np.abs(floats - central).max() / scale)
        assert worst_exact < 1e-12, worst_exact
        assert worst_central < 1e-6, worst_central   # the differences' own error


def test_the_residual_models_clip_and_rate_terms_are_reached():
    """The random inputs above reach both branches of the bound and the rate terms."""
    rng = np.random.default_rng(4)
    model = _layout_model(('residual_model',), rng, clip=True)
    assert model.paired
    bound = model.source(model.layout.vector())
    clipped = free = 0
    for left, right, rate_l, rate_r in rng.uniform(-12.0, 12.0, (60, 4)):
        base = bound.base.scalar_twist(left, right)
        out = bound.scalar_memoryless(left, right, 0.0, bound.base.scalar_twist(rate_l, rate_r),
                                      base)
        change = abs(out[0] - base[0])
        limit = abs(base[0]) + abs(base[2]) * 2.0
        clipped += change >= limit * (1 - 1e-12)
        free += change < limit * (1 - 1e-9)
    assert clipped > 5 and free > 5


def test_layouts_not_covered_keep_the_central_differences():
    rng = np.random.default_rng(1)
    # the residual model's coefficients free: no float partial for them
    model = _layout_model(('residual_model',), rng)
    layout = model.layout
    index = residual.coefficient_names().index('vx_v')
    free = layout.free + ((0, index),)
    assert scalar_tangents(model.source(layout.vector()), free) is None
    # a ROC base (not linear in the wheel speeds)
    roc = LayoutModel(online_layout('roc', GEOMETRY, {}, {'speed_slip': {'k': 0.1}},
                                    ('speed_slip',)))
    k = roc.layout.vector()
    assert scalar_tangents(roc.source(k), roc.layout.free) is None
    fallback = LayoutUncertainty.of_layout(roc, k, GEOMETRY, np.eye(k.size) * 1e-4)
    assert fallback.tangents is None and len(fallback.pairs) == k.size
    got = np.array(fallback.twist_jacobian(0.0, 0.0, 0.0, (3.0, 2.0))).T
    np.testing.assert_allclose(got, roc.twist_gradient(k, GEOMETRY, 3.0, 2.0), rtol=1e-6,
                               atol=1e-9)
    # a covered layout carries no perturbed models
    covered = _layout_model(('speed_slip',), rng)
    k = covered.layout.vector()
    exact = LayoutUncertainty.of_layout(covered, k, GEOMETRY, np.eye(k.size) * 1e-4)
    assert exact.tangents is not None and exact.pairs == ()
    assert set(SCALAR_PARTIALS) == {'speed_slip', 'direction_asymmetry', 'lateral_skid',
                                    'icr_offset', 'ratio_yaw_slip', 'acceleration_slip',
                                    'residual_model'}


def test_the_batch_residual_model_computes_only_its_terms_in_use_bit_for_bit():
    """The batch form evaluates the terms with a coefficient only: the full library's sums."""
    rng = np.random.default_rng(11)
    ext = get_extension('residual_model')
    count = len(residual.TERMS)
    twist = rng.uniform(-4.0, 4.0, (500, 3))
    rate = rng.uniform(-5.0, 5.0, (500, 3))
    for used in (0, 2, 9, count):
        values = _residual_values(rng, clip=True)
        names = residual.coefficient_names()
        keep = set(rng.choice(count, used, replace=False).tolist())
        for i, name in enumerate(names):
            if i % count not in keep:
                values[name] = 0.0
        k = ext.vector(values)
        coef = k[:len(names)].tolist()
        ranges = k[len(names):len(names) + 8].tolist()
        full = residual.correction(coef, residual.features(ranges, twist, rate))
        terms = residual.used_terms(coef)
        assert set(terms) == keep
        planned = residual.correction(coef, residual.features(ranges, twist, rate, terms), terms)
        assert np.array_equal(planned, full)
        # the partials by coefficients not in use still read their terms
        wanted = [names.index(f'vx_{residual.TERMS[j][0]}') for j in range(0, count, 5)]
        d_k = ext.partials(k, twist, twist[:, 0], twist[:, 1], 0.0, rate, wanted,
                           inputs=False)[2]
        phi = residual.features(ranges, twist, rate)
        gain = values['gain_vx']
        change = full * np.array([values['gain_vx'], values['gain_vy'], values['gain_wz']])
        bound = np.abs(twist[:, 0]) + np.abs(twist[:, 2]) * SLIP_LEVER_M
        free = np.abs(change[:, 0]) <= bound
        for c, j in enumerate(range(0, count, 5)):
            np.testing.assert_array_equal(d_k[free, 0, c], phi[free, j] * gain)


def test_a_layouts_covariance_read_is_the_base_forms_to_rounding():
    rng = np.random.default_rng(9)
    model = _layout_model(('speed_slip', 'residual_model'), rng)
    k = model.layout.vector()
    for size in (k.size, 0):
        q, _ = np.linalg.qr(rng.normal(size=(k.size, k.size)))
        cov = (q * np.logspace(-3, -9, k.size)) @ q.T
        if size == 0:
            cov[:, 0] = cov[0, :] = 0.0   # a singular covariance
        uncertainty = LayoutUncertainty.of_layout(model, k, GEOMETRY, cov)
        for _ in range(20):
            sens = [tuple(v) for v in rng.normal(0.0, 2.0, (k.size, 3)).tolist()]
            fast = np.array(uncertainty.pose_covariance(sens))
            base = np.array(super(LayoutUncertainty, uncertainty).pose_covariance(sens))
            np.testing.assert_allclose(fast, base, rtol=0, atol=1e-13 * np.abs(base).max())
