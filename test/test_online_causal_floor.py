"""The causal floor of the long stretches (lab.bench.online_causal).

The oracle refits the offline calibrator on the current ground's data seen so far. On an
unchanging ground its last fit is the calibrator's fit on the whole drive; cutting the drive
short changes nothing before the cut (it never uses data after its time).
"""

from lab.bench.online_causal import causal_fits, causal_poses, prior_fits
from lab.studies import online as study
import numpy as np
import pytest
from skidkin_ros.core.calibration.segments import HorizonOptions, usable_segments
from skidkin_ros.core.calibration.weighting import fit_model_iterated
from skidkin_ros.core.drive import Drive, PoseTrack, WheelSamples
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.odometry.interval import DEFAULT_INTERVAL
from skidkin_ros.core.odometry.noise import NoiseModel
from skidkin_ros.sim.simulate import DEFAULT_TRUE_PARAMS, SimConfig, simulate


@pytest.fixture(scope='module')
def drive():
    sim = simulate(SimConfig(duration_s=60.0, seed=5))
    return sim, study._reference(sim, np.random.default_rng(5))


def test_on_one_ground_it_converges_to_the_whole_drive_fit(drive):
    sim, reference = drive
    geometry = sim.config.geometry
    fits = causal_fits(sim.wheels, reference, geometry, sim.start_ns, sim.end_ns + 1)
    assert len(fits) >= 5
    times = [t for t, _, _ in fits]
    assert times == sorted(times) and times[0] > sim.start_ns
    whole = fit_model_iterated(study.MODEL, geometry, usable_segments(
        [Drive('all', sim.wheels, reference)], HorizonOptions().train_segments(), 'training'))
    names = get_model(study.MODEL).param_names
    assert [fits[-1][1][n] for n in names] == pytest.approx([whole.values[n] for n in names],
                                                            abs=1e-9)
    # and it approaches the truth as the data grow (the first fit is the furthest)
    gap = [max(abs(v[n] - DEFAULT_TRUE_PARAMS[n]) / abs(DEFAULT_TRUE_PARAMS[n]) for n in names)
           for _, v, _ in fits]
    assert gap[-1] < 0.03 and gap[-1] < gap[0]


def test_it_never_uses_data_after_its_time(drive):
    sim, reference = drive
    geometry = sim.config.geometry
    model = get_model(study.MODEL)
    start = model.bind(DEFAULT_TRUE_PARAMS, geometry)
    cut = sim.start_ns + 45_000_000_000
    n = int(np.searchsorted(sim.wheels.t_ns, cut, side='right'))
    # a change at 20 s, known: the second ground's fits are of its own data only
    change = sim.start_ns + 20_000_000_000
    on_new = sim.wheels.t_ns >= change

    def run(wheels, ref, end):
        fits = [causal_fits(wheels, ref, geometry, sim.start_ns, change),
                causal_fits(wheels, ref, geometry, change, end)]
        schedules = [[(t, model.bind(v, geometry)) for t, v, _ in f] for f in fits]
        return fits, causal_poses(wheels, on_new[:len(wheels)], (start, start), schedules,
                                  DEFAULT_INTERVAL)

    full_fits, full = run(sim.wheels, reference, sim.end_ns + 1)
    on = reference.t_ns <= cut
    short_fits, short = run(
        WheelSamples(sim.wheels.t_ns[:n], sim.wheels.omega_l[:n], sim.wheels.omega_r[:n]),
        PoseTrack(reference.t_ns[on], reference.x[on], reference.y[on], reference.yaw[on]),
        cut + 1)
    assert short_fits[1] and len(short_fits[1]) < len(full_fits[1])
    assert [f[0] for f in short_fits[1]] == [f[0] for f in full_fits[1]][:len(short_fits[1])]
    np.testing.assert_array_equal(short, full[:n])
    # the refits do move the poses: with the start model throughout they differ
    plain = causal_poses(sim.wheels, on_new, (start, start), ([], []), DEFAULT_INTERVAL)
    assert np.abs(plain[:n] - full[:n]).max() > 1e-3
    # and no fit is used before the pose it needs is seen: up to the first fit, the start's
    assert not full_fits[0]   # 20 s: too few segments on the first ground
    # (used from the step after the first wheel sample at or after that pose)
    first = int(np.searchsorted(sim.wheels.t_ns, full_fits[1][0][0], side='left'))
    np.testing.assert_array_equal(plain[:first + 1], full[:first + 1])
    assert np.abs(plain[first + 1] - full[first + 1]).max() > 0


def test_the_prior_refit_learns_from_the_first_metres_and_only_from_the_past(drive):
    sim, reference = drive
    geometry = sim.config.geometry
    names = get_model(study.MODEL).param_names
    start = {n: DEFAULT_TRUE_PARAMS[n] * (0.8 if n.startswith('alpha') else 1.0) for n in names}
    noise = NoiseModel(1e-3, 1e-3, 1e-4, 1e-3)
    cut = sim.start_ns + 20_000_000_000
    full = prior_fits(sim.wheels, reference, geometry, sim.start_ns, sim.end_ns + 1, start,
                      noise, 0.5)
    on = reference.t_ns <= cut
    n = int(np.searchsorted(sim.wheels.t_ns, cut, side='right'))
    short = prior_fits(
        WheelSamples(sim.wheels.t_ns[:n], sim.wheels.omega_l[:n], sim.wheels.omega_r[:n]),
        PoseTrack(reference.t_ns[on], reference.x[on], reference.y[on], reference.yaw[on]),
        geometry, sim.start_ns, cut + 1, start, noise, 0.5)
    assert 0 < len(short) < len(full)
    # the same fits (to rounding: the segments are padded to the longest of each cut)
    assert [t for t, _, _ in short] == [t for t, _, _ in full[:len(short)]]
    for (_, v, _), (_, w, _) in zip(short, full):
        assert [v[n] for n in names] == pytest.approx([w[n] for n in names], rel=1e-7)
    # a probe inside the first segment already moves alpha from the 20 % wrong start; at the
    # end the speed gains are within 2 % of the truth
    assert full[0][2] < 2.0 and full[0][1]['alpha_l'] > start['alpha_l'] + 0.02
    for name in ('alpha_l', 'alpha_r'):
        assert full[-1][1][name] == pytest.approx(DEFAULT_TRUE_PARAMS[name], rel=0.02)
