"""Extensions in closed form, the augmented model's state, and streaming == batch."""

import math

import numpy as np
import pytest
from skidkin_ros.core.calibration.fitting import predict_end_poses
from skidkin_ros.core.calibration.predictor import SegmentPredictor
from skidkin_ros.core.calibration.segments import cut_segments, SegmentOptions
from skidkin_ros.core.drive import Drive, PoseTrack, WheelSamples
from skidkin_ros.core.kinematics.augmented import AugmentedModel, lag_factors
from skidkin_ros.core.kinematics.extensions import (EXTENSION_NAMES, EXTENSIONS, FitHints,
                                                    get_extension, LIBRARY, SPARSE_FEATURES,
                                                    sparse_features)
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.config import OdometryConfig, parameter_schema, parse_extensions
from skidkin_ros.core.odometry.integrator import (IntegratorLimits, rollout, rollout_stream,
                                                  SampleStatus, step_scalar,
                                                  StreamingIntegrator)
from skidkin_ros.core.odometry.interval import interval_speed
from skidkin_ros.core.odometry.odometer import predict_wheels
from skidkin_ros.errors import ParameterError
from skidkin_ros.sim.effects import EFFECT_NAMES

GEOM = Geometry(0.1651, 0.555)
BASE = get_model('edd_symmetric').bind({'alpha': 0.9, 'b_hat': 0.8}, GEOM)


def augmented(values):
    return AugmentedModel('edd_symmetric', list(values)).bind(BASE, values)


def test_every_simulator_effect_has_an_extension_and_specs_are_complete():
    assert set(EFFECT_NAMES) <= set(EXTENSION_NAMES)
    assert 'sparse_correction' in EXTENSIONS
    for ext in EXTENSIONS.values():
        assert ext.params and ext.formula and ext.signal
        for spec in ext.params:
            assert spec.unit and spec.description and spec.lower <= spec.default_for(None)
        # defaults are neutral: the base model is unchanged
        k = ext.vector({})
        twist = BASE.twist(np.array([1.0, -2.0, 3.0]), np.array([2.0, -1.0, 1.5]))
        np.testing.assert_array_equal(
            ext.apply(k, twist, np.array([1.0, -2.0, 3.0]), np.array([2.0, -1.0, 1.5]),
                      np.zeros(3)), twist)


def test_each_entry_says_how_to_start_scan_and_rank_it():
    """One registry entry feeds the diagnosis: no extension is special-cased there."""
    hints = FitHints(lag_s=0.12, convention_s=-0.025, period_s=0.05, duration_s=100.0)
    for ext in EXTENSIONS.values():
        start = ext.start_values(hints)
        assert list(start) == list(ext.param_names), ext.name
        assert all(spec.contains(start[spec.name]) for spec in ext.params), ext.name
        assert set(ext.fitted) | set(ext.scan) <= set(ext.param_names)
        assert ext.learned or ext.fitted, ext.name
        if ext.scan:
            low, high = ext.scan_range(hints)
            assert 0.0 <= low < high
        if ext.short_alias is not None:
            param, other = ext.short_alias
            assert param in ext.fitted
            assert get_extension(other).complexity() < ext.complexity()
    assert get_extension('time_offset').start_values(hints) == {'offset_s': pytest.approx(0.095)}
    assert get_extension('first_order_lag').start_values(hints) == {'tau_s': pytest.approx(0.12)}
    assert get_extension('first_order_lag').start_values(FitHints(lag_s=9.0)) == {'tau_s': 1.5}
    assert get_extension('terrain_regime').scan_range(hints) == (0.0, 100.0)
    # fewer parameters first, then stateless before stateful; a library counts its terms
    assert get_extension('icr_offset').complexity() == (1, 0)
    assert get_extension('first_order_lag').complexity() == (1, 1)
    assert get_extension('ratio_yaw_slip').complexity() == (2, 0)
    assert get_extension('sparse_correction').complexity(('vx_v', 'wz_w')) == (2, 0)


def test_library_terms_are_one_registry():
    assert SPARSE_FEATURES == tuple((term.name, term.unit) for term in LIBRARY)
    ext = get_extension('sparse_correction')
    assert len(ext.params) == 3 * len(LIBRARY) and ext.library


def test_scalar_forms_equal_the_array_forms_bit_for_bit():
    # The node runs the float forms once per sample; fitting and offline tools run the array
    # forms: they must agree exactly, so a calibrated model behaves the same live.
    rng = np.random.default_rng(11)
    wl = np.concatenate([rng.uniform(-6, 6, 400), [0.0, 2.0, -2.0, 3.0, 0.0]])
    wr = np.concatenate([rng.uniform(-6, 6, 400), [0.0, 2.0, 2.0, 0.0, 1.0]])
    t_s = rng.uniform(0, 60, wl.size)
    rate = rng.normal(0.0, 2.0, (wl.size, 3))
    rate[::5] = 0.0
    with_scalar = [n for n in EXTENSION_NAMES if get_extension(n).scalar_apply() is not None]
    assert set(EXTENSION_NAMES) - set(with_scalar) == {'sparse_correction'}
    for name in with_scalar:
        ext = get_extension(name)
        k = np.array([rng.uniform(spec.lower if math.isfinite(spec.lower) else -1, min(
            spec.upper, 2.0)) for spec in ext.params]) if ext.params else np.zeros(0)
        k = np.where(k == 0.0, 0.1, k)
        array_form = ext.apply(k, BASE.twist(wl, wr), wl, wr, t_s, rate)
        scalar = ext.scalar_apply()
        for i in range(wl.size):
            vx, vy, w = BASE.scalar_twist(float(wl[i]), float(wr[i]))
            got = scalar(tuple(k.tolist()), vx, vy, w, float(wl[i]), float(wr[i]), float(t_s[i]),
                         tuple(rate[i].tolist()))
            assert got == tuple(array_form[i].tolist()), (name, i)
    model = augmented({n: ALL_VALUES[n] for n in ALL_VALUES if n != 'sparse_correction'})
    for i in range(0, wl.size, 7):
        assert model.scalar_memoryless(float(wl[i]), float(wr[i]), float(t_s[i]),
                                       tuple(rate[i].tolist())) == tuple(
            model.memoryless(wl[i], wr[i], t_s[i], rate[i]).tolist())


@pytest.mark.parametrize('name,values,check', [
    ('speed_slip', {'k': 0.2}, lambda b, t: (b[0] * (1 - 0.2 * abs(b[0])), b[1], b[2])),
    ('lateral_skid', {'k': 0.05}, lambda b, t: (b[0], 0.05 * b[0] * b[2], b[2])),
    ('icr_offset', {'x_m': 0.2}, lambda b, t: (b[0], 0.2 * b[2], b[2])),
    ('direction_asymmetry', {'k': 0.3},
     lambda b, t: (b[0] * (1 - 0.3 * min(max(-b[0] / 0.05, 0), 1)), b[1], b[2])),
    ('terrain_regime', {'k': 0.25, 'switch_s': 1.0},
     lambda b, t: ((b[0] * 0.75, b[1], b[2] * 0.75) if t >= 1.0 else tuple(b))),
])
@pytest.mark.parametrize('wl,wr,t_s', [(3.0, 4.0, 0.5), (-3.0, -2.0, 1.5), (2.0, -2.0, 2.0)])
def test_memoryless_formulas(name, values, check, wl, wr, t_s):
    base = BASE.twist(wl, wr)
    ext = get_extension(name)
    out = ext.apply(ext.vector(values), base, np.float64(wl), np.float64(wr), t_s)
    np.testing.assert_allclose(out, check(base, t_s), atol=1e-12)


def test_ratio_yaw_slip_peaks_at_half_speed_ratio():
    ext = get_extension('ratio_yaw_slip')
    k = ext.vector({'k': 0.4})
    for wl, wr, expected_loss in ((2.0, 4.0, 0.4), (4.0, 4.0, 0.4 * math.exp(-(0.5 / 0.15) ** 2)),
                                  (-2.0, 4.0, 0.0)):
        base = BASE.twist(wl, wr)
        out = ext.apply(k, base, np.float64(wl), np.float64(wr), 0.0)
        assert out[2] == pytest.approx(base[2] * (1 - expected_loss), abs=1e-12)


def test_sparse_correction_adds_the_library_terms():
    ext = get_extension('sparse_correction')
    assert len(ext.params) == 3 * len(SPARSE_FEATURES)
    k = ext.vector({'vx_v_abs_v': -0.1, 'wz_w': 0.05})
    base = BASE.twist(3.0, 5.0)
    out = ext.apply(k, base, 3.0, 5.0, 0.0)
    assert out[0] == pytest.approx(base[0] - 0.1 * base[0] * abs(base[0]))
    assert out[2] == pytest.approx(base[2] * 1.05)


@pytest.mark.parametrize('interval, step_ns', [('starting', 500_000_000),
                                               ('ending', 450_000_000)])
def test_lag_is_the_exact_response_to_a_held_input(interval, step_ns):
    model = augmented({'first_order_lag': {'tau_s': 0.3}})
    t_ns = np.arange(0, 41) * 50_000_000
    wl = np.where(t_ns >= 500_000_000, 4.0, 0.0)
    # under ending, the sample at 0.5 s describes [0.45, 0.5]: the input steps at 0.45 s
    poses = rollout_stream(model, t_ns, wl, wl, interval=interval)
    streamed = predict_wheels(WheelSamples(t_ns, wl, wl), model, interval=interval)
    v_ss = BASE.twist(4.0, 4.0)[0]
    # step at t0: x(t) = v (T - tau (1 - exp(-T / tau))), T = t - t0
    for i in (20, 30, 40):
        elapsed = (t_ns[i] - step_ns) * 1e-9
        assert streamed.poses[i, 0] == pytest.approx(poses[i, 0], rel=1e-12, abs=1e-12)
        expected = v_ss * (elapsed - 0.3 * (1 - math.exp(-elapsed / 0.3)))
        assert poses[i, 0] == pytest.approx(expected, rel=1e-12, abs=1e-12)
    d, g = lag_factors(np.array([0.0, 0.05]), 0.3)
    assert g[0] == 1.0 and d[1] == pytest.approx(math.exp(-0.05 / 0.3))


def _random_drive(seed, n=400):
    rng = np.random.default_rng(seed)
    t_ns = np.cumsum(rng.integers(30_000_000, 70_000_000, n)).astype(np.int64)
    t_ns[n // 4] = t_ns[n // 4 - 1]      # duplicate stamp
    t_ns[n * 5 // 8:] += 2_000_000_000  # a gap longer than max_dt
    wl, wr = rng.uniform(-5, 5, (2, n))
    return t_ns, wl, wr


ALL_VALUES = {'time_offset': {'offset_s': 0.07}, 'first_order_lag': {'tau_s': 0.2},
              'speed_slip': {'k': 0.2}, 'lateral_skid': {'k': 0.05},
              'direction_asymmetry': {'k': 0.2}, 'ratio_yaw_slip': {'k': 0.3},
              'icr_offset': {'x_m': 0.1},
              'terrain_regime': {'k': 0.2, 'switch_s': 6.0},
              'sparse_correction': {'vx_v_abs_v': -0.05}}


# Per-component lags exclude first_order_lag (one lag per model): their own combinations.
PER_COMPONENT = {'forward_lag': {'tau_s': 0.25}, 'yaw_lag': {'tau_s': 0.15},
                 'component_lags': {'tau_v_s': 0.25, 'tau_w_s': 0.1},
                 'acceleration_slip': {'tau_s': 0.12}, 'lateral_skid': {'k': 0.05},
                 'sparse_correction': {'vx_dv_up': -0.1, 'wz_dw': 0.02}}


@pytest.mark.parametrize('names', [('first_order_lag',), ('terrain_regime', 'lateral_skid'),
                                   tuple(ALL_VALUES), ('forward_lag', 'acceleration_slip'),
                                   ('yaw_lag', 'lateral_skid'),
                                   ('component_lags', 'acceleration_slip', 'sparse_correction')])
def test_streaming_and_batch_agree_sample_for_sample_with_state(names):
    model = augmented({n: {**ALL_VALUES, **PER_COMPONENT}[n] for n in names})
    t_ns, wl, wr = _random_drive(3)
    limits = IntegratorLimits(max_dt_s=0.5)
    streamed = predict_wheels(WheelSamples(t_ns, wl, wr), model, limits)
    batch = rollout_stream(model, t_ns, wl, wr, max_dt_s=0.5)
    # Two code paths (the streaming integrator, the batch rollout) sum the same terms in a
    # different order, so equality is to rounding: a few ulps of the pose's magnitude, not bit
    # for bit (numpy 2.4 moved the last bit on one sample). The node and predict share one path
    # and stay equal bit for bit (test_node_augmented).
    ulps = 8 * np.finfo(float).eps * np.maximum(1.0, np.abs(batch))
    assert np.all(np.abs(streamed.poses - batch) <= ulps)
    assert streamed.status.count(SampleStatus.GAP) == 1
    assert streamed.status.count(SampleStatus.DUPLICATE_STAMP) == 1
    # the state matters: without it (no lag, no regime) the path differs
    plain = rollout_stream(BASE, t_ns, wl, wr, max_dt_s=0.5)
    assert np.abs(plain[-1] - batch[-1]).max() > 1e-3


def test_time_offset_shifts_published_stamps_only():
    model = augmented({'time_offset': {'offset_s': 0.07}})
    t_ns, wl, wr = _random_drive(4, 50)
    result = predict_wheels(WheelSamples(t_ns, wl, wr), model, IntegratorLimits(max_dt_s=5))
    plain = predict_wheels(WheelSamples(t_ns, wl, wr), BASE, IntegratorLimits(max_dt_s=5))
    assert model.output_offset_ns == 70_000_000
    assert np.array_equal(result.t_ns, t_ns + 70_000_000)
    assert np.array_equal(result.poses, plain.poses)


def test_base_model_speed_is_unchanged_and_reset_clears_the_state():
    model = augmented({'first_order_lag': {'tau_s': 0.5}})
    stream = StreamingIntegrator(model, interval='starting')
    stream.step(0, 0.0, 0.0)
    stream.step(100_000_000, 5.0, 5.0)
    assert stream.state is not None and stream.held_twist[0] == 0.0  # lags behind the input
    # ending: the first interval starts the response at its own input, later ones lag
    ending = StreamingIntegrator(model, interval='ending')
    for t_ns, speed in ((0, 0.0), (100_000_000, 0.0), (200_000_000, 5.0)):
        ending.step(t_ns, speed, speed)
    # the speed of 5 rad/s over [0.1, 0.2] s has moved the response 1 - exp(-0.1 / 0.5) of the way
    assert ending.held_twist[0] == pytest.approx(BASE.twist(5.0, 5.0)[0] * (1 - math.exp(-0.2)))
    stream.reset()
    assert stream.state is None
    stream.step(0, 5.0, 5.0)
    assert stream.held_twist[0] == pytest.approx(BASE.twist(5.0, 5.0)[0])  # starts settled
    plain = StreamingIntegrator(BASE)
    plain.step(0, 1.0, 1.0)
    assert plain.state is None  # a base model never builds a state


def _drive_with_truth(seed):
    t_ns, wl, wr = _random_drive(seed, 300)
    t_ns[300 * 5 // 8:] -= 2_000_000_000  # no gap here
    t_ns = np.unique(t_ns)
    wl, wr = wl[:t_ns.size], wr[:t_ns.size]
    truth = rollout(BASE.twist(wl[1:], wr[1:]), np.diff(t_ns) * 1e-9)  # interval: ending
    keep = np.arange(0, t_ns.size, 2)
    return Drive(f'd{seed}', WheelSamples(t_ns, wl, wr),
                 PoseTrack(t_ns[keep], *truth[keep].T))


def _window_by_steps(stamps, twists, s_a, s_b, start):
    """Integrate one window step by step: each piece holds the last sample stamped before it."""
    inside = stamps[(stamps > s_a) & (stamps < s_b)]
    breaks = np.concatenate([[s_a], inside, [s_b]])
    pose = np.asarray(start, dtype=float)
    for lo, hi in zip(breaks[:-1], breaks[1:]):
        held = max(int(np.searchsorted(stamps, lo, side='right')) - 1, 0)
        pose = rollout(twists[held][None], [(hi - lo) * 1e-9], pose)[-1]
    return pose


def test_segment_predictor_windows_agree_with_step_by_step_integration():
    """Windows inside one interval, on stamps, before the first and after the last, over a gap."""
    from skidkin_ros.core.calibration.segments import SegmentSet
    drives = []
    for seed in (11, 12):
        t_ns, wl, wr = _random_drive(seed, 120)
        t_ns = np.unique(t_ns)
        drives.append(Drive(f'd{seed}', WheelSamples(t_ns, wl[:t_ns.size], wr[:t_ns.size]),
                            PoseTrack(t_ns, *np.zeros((3, t_ns.size)))))
    rng = np.random.default_rng(5)
    rows = []
    for d, drive in enumerate(drives):
        t = drive.wheels.t_ns
        gap = int(np.argmax(np.diff(t)))
        rows += [(d, t[3] + 1_000_000, t[3] + 2_000_000),  # inside one interval
                 (d, t[5], t[9]),                          # exactly on stamps
                 (d, t[0] - 80_000_000, t[4] + 7),          # starts before the first stamp
                 (d, t[-3] - 5, t[-1] + 90_000_000),        # ends after the last
                 (d, t[gap - 2] + 3, t[gap + 3] - 3),       # across the gap
                 (d, t[0], t[-1])]                          # the whole drive
    drive_ix, t_a, t_b = (np.array(col) for col in zip(*rows))
    start = rng.normal(size=(len(rows), 3))
    empty = np.zeros((len(rows), 1))
    segments = SegmentSet(drive_ix, t_a, t_b, start, start.copy(), empty, empty, empty,
                          np.ones(len(rows)))
    predictor = SegmentPredictor(drives, segments)
    for source in (BASE, augmented({'time_offset': {'offset_s': 0.0123}})):
        offset = int(getattr(source, 'output_offset_ns', 0))
        twists = predictor.mean_twists(source).reshape(len(drives), -1, 3)
        expected = [_window_by_steps(drives[d].wheels.t_ns, twists[d], a - offset, b - offset,
                                     start[i]) for i, (d, a, b) in enumerate(rows)]
        np.testing.assert_allclose(predictor.predict_ends(source), expected, atol=1e-9)
        keep = np.array([1, 4, 7])
        np.testing.assert_allclose(predictor.predict_ends(source, keep),
                                   np.asarray(expected)[keep], atol=1e-9)


def test_segment_predictor_matches_the_fitting_code_and_shifts_windows():
    drives = [_drive_with_truth(5), _drive_with_truth(6)]
    segments = cut_segments(drives, SegmentOptions(horizon_m=1.0))
    predictor = SegmentPredictor(drives, segments)
    expected = predict_end_poses(BASE.model, BASE.k, GEOM, segments)
    np.testing.assert_allclose(predictor.predict_ends(BASE), expected, atol=1e-12)
    np.testing.assert_allclose(predictor.errors(BASE), 0.0, atol=1e-9)
    shifted = augmented({'time_offset': {'offset_s': 0.1}})
    assert np.abs(predictor.errors(shifted)).max() > 1e-3


def test_parameters_file_schema_holds_the_augmented_model():
    names = {entry.name for entry in parameter_schema()}
    assert {'augmented.base', 'augmented.extensions', 'augmented.time_offset.offset_s',
            'augmented.first_order_lag.tau_s'} <= names
    config = OdometryConfig.from_flat({
        'model': 'augmented', 'augmented.base': 'edd_symmetric',
        'augmented.extensions': 'lateral_skid, time_offset',
        'models.edd_symmetric.alpha': 0.9, 'models.edd_symmetric.b_hat': 0.8,
        'augmented.lateral_skid.k': 0.05, 'augmented.time_offset.offset_s': 0.03})
    bound = config.bound_model()
    assert bound.extensions == ('time_offset', 'lateral_skid')
    assert bound.output_offset_ns == 30_000_000
    np.testing.assert_allclose(bound.twist(3.0, 4.0),
                               get_extension('lateral_skid').apply(
                                   np.array([0.05]), BASE.twist(3.0, 4.0), 3.0, 4.0, 0.0))
    assert parse_extensions('') == ()
    with pytest.raises(ParameterError, match='unknown extension'):
        OdometryConfig.from_flat({'augmented.extensions': 'time_ofset'})
    with pytest.raises(ParameterError, match='outside its allowed range'):
        OdometryConfig.from_flat({'augmented.first_order_lag.tau_s': -1.0})


def test_constant_rate_lag_uses_the_filter_path_and_still_matches_streaming():
    model = augmented({'first_order_lag': {'tau_s': 0.15}, 'speed_slip': {'k': 0.1}})
    rng = np.random.default_rng(8)
    t_ns = np.arange(600, dtype=np.int64) * 50_000_000
    wl = np.repeat(rng.uniform(-5, 5, 30), 20)
    wr = np.repeat(rng.uniform(-5, 5, 30), 20)
    for interval in ('ending', 'midpoint'):
        streamed = predict_wheels(WheelSamples(t_ns, wl, wr), model, interval=interval)
        batch = rollout_stream(model, t_ns, wl, wr, max_dt_s=0.5, interval=interval)
        np.testing.assert_allclose(batch, streamed.poses, rtol=0, atol=1e-9)
    # the published twists are the held samples' under starting
    streamed = predict_wheels(WheelSamples(t_ns, wl, wr), model, interval='starting')
    batch = rollout_stream(model, t_ns, wl, wr, max_dt_s=0.5, interval='starting')
    np.testing.assert_allclose(batch, streamed.poses, rtol=0, atol=1e-9)
    held, _ = model.intervals(t_ns[None], wl[None], wr[None],
                              np.append(np.diff(t_ns) * 1e-9, 0.0)[None],
                              np.zeros((1, t_ns.size), bool))
    np.testing.assert_allclose(held[0], streamed.twists, rtol=0, atol=1e-12)


def test_per_component_lags_act_on_their_component_only():
    # A step of both wheels into a turn at 0.5 s: forward speed and yaw rate both jump.
    t_ns = np.arange(0, 41) * 50_000_000
    wl = np.where(t_ns >= 500_000_000, 2.0, 0.0)
    wr = np.where(t_ns >= 500_000_000, 4.0, 0.0)
    plain = BASE.twist(2.0, 4.0)
    cases = {'forward_lag': (True, False), 'yaw_lag': (False, True),
             'component_lags': (True, True), 'first_order_lag': (True, True)}
    for name, (v_lags, w_lags) in cases.items():
        ext = get_extension(name)
        values = dict.fromkeys(ext.param_names, 0.3)
        stream = StreamingIntegrator(augmented({name: values}), interval='starting')
        for i in range(12):  # up to 0.55 s: one sample after the step
            stream.step(int(t_ns[i]), float(wl[i]), float(wr[i]))
        vx, _, wz = stream.held_twist
        # exact held-input response one 50 ms step after the jump: 1 - exp(-0.05 / 0.3)
        frac = 1.0 - math.exp(-0.05 / 0.3)
        assert vx == pytest.approx(plain[0] * (frac if v_lags else 1.0), rel=1e-12), name
        assert wz == pytest.approx(plain[2] * (frac if w_lags else 1.0), rel=1e-12), name


def test_two_lags_cannot_be_combined():
    with pytest.raises(ParameterError, match='cannot be combined'):
        AugmentedModel('edd_symmetric', ['forward_lag', 'yaw_lag'])
    assert get_extension('component_lags').complexity() == (2, 1)
    assert get_extension('forward_lag').complexity() == (1, 1)


def test_acceleration_slip_takes_speed_only_while_speeding_up():
    ext = get_extension('acceleration_slip')
    k = ext.vector({'tau_s': 0.1})
    base = BASE.twist(4.0, 4.0)  # straight ahead
    v = base[0]
    for dv, expected in ((2.0, v - 0.2), (-2.0, v), (0.0, v), (1e3, 0.0)):
        out = ext.apply(k, base, 4.0, 4.0, 0.0, np.array([dv, 0.0, 0.0]))
        assert out[0] == pytest.approx(expected, abs=1e-12)
        assert out[2] == base[2]
    backward = BASE.twist(-4.0, -4.0)
    out = ext.apply(k, backward, -4.0, -4.0, 0.0, np.array([-2.0, 0.0, 0.0]))
    assert out[0] == pytest.approx(backward[0] + 0.2)  # speeding up backward: less backward


def test_the_rate_is_the_backward_difference_of_the_base_twist():
    # A ramp of both wheels: the base forward speed grows by 0.9 r 1 rad/s per 0.1 s.
    model = augmented({'acceleration_slip': {'tau_s': 0.1}})
    stream = StreamingIntegrator(model, interval='starting')
    accel = 0.9 * GEOM.wheel_radius * 10.0  # m/s^2 of forward speed
    for i in range(6):
        stream.step(i * 100_000_000, float(i), float(i))
    v_now = BASE.twist(5.0, 5.0)[0]
    assert stream.held_twist[0] == pytest.approx(v_now - 0.1 * accel, rel=1e-9)
    # the library's derivative terms see the same rate
    features = dict(zip((t.name for t in LIBRARY), sparse_features(
        BASE.twist(5.0, 5.0), np.array([accel, 0.0, 0.0]))))
    assert features['dv'] == features['dv_up'] == pytest.approx(accel)
    assert features['dw'] == 0.0


@pytest.mark.parametrize('interval', ['ending', 'midpoint'])
@pytest.mark.parametrize('values', [
    {'acceleration_slip': {'tau_s': 0.12}},
    {'sparse_correction': {'vx_dv': -0.1, 'vx_dv_up': -0.05, 'wz_dw': 0.03}},
], ids=['acceleration_slip', 'sparse_derivatives'])
def test_the_published_twist_of_a_rate_model_is_the_one_the_pose_integrates(interval, values):
    # Without a lag the twist is constant over each interval: the published twist times dt is
    # the pose increment, the rate term included (before: the rate term was left out).
    model = augmented(values)
    stream = StreamingIntegrator(model, interval=interval)
    t_ns = np.arange(80, dtype=np.int64) * 50_000_000
    ramp = np.concatenate([np.linspace(0.5, 6.0, 40), np.linspace(6.0, 0.5, 40)])
    wl, wr = ramp, ramp * (1.0 + 0.3 * np.sin(np.arange(80) / 7.0))
    rate_terms = 0
    for t, left, right in zip(t_ns, wl, wr):
        before = stream.held_speeds
        result = stream.step(int(t), float(left), float(right))
        if result.status is not SampleStatus.INTEGRATED:
            continue
        vx, vy, w = result.twist
        x, y, yaw = result.start_pose
        moved = step_scalar(x, y, yaw, vx, vy, w, result.dt_s)[:3]
        assert moved == result.pose
        assert result.twist == result.step_twist
        # the twist of the interval's speeds without the rate term
        held = [interval_speed(a, b, interval) for a, b in zip(before, (left, right))]
        steady = model.scalar_memoryless(*held, 0.0)
        rate_terms += abs(vx - steady[0]) > 1e-3 or abs(w - steady[2]) > 1e-3
    # the rate terms are there to be seen (acceleration slip: only while speeding up)
    assert rate_terms >= 35
