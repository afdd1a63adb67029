"""The residual model's window terms on a careless recording's wheel stamps."""

from dataclasses import replace

from lab.studies.effects import GEOMETRY, sim_drives, SIM_INTERVAL
from lab.studies.unnamed_effects import draw_effects
import numpy as np
from skidkin_ros.core.calibration.diagnosis import DiagnosisOptions
from skidkin_ros.core.calibration.diagnosis.regression import fit_residual_model
from skidkin_ros.core.calibration.diagnosis.residuals import pose_samples
from skidkin_ros.core.calibration.diagnosis.window_features import window_terms
from skidkin_ros.core.calibration.fitting import fit_model
from skidkin_ros.core.calibration.segments import cut_segments
from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.core.kinematics import residual
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.timeunits import s_to_ns


def _setup():
    """Return a 40 s drive with a turn asymmetry no extension names, and its calibrated base."""
    effects = draw_effects(np.random.default_rng(11), count=1, families=('turn_asymmetry',),
                           strength=(0.25, 0.25))
    drive = sim_drives(effects, [1], 40.0)[0]
    options = DiagnosisOptions(interval=SIM_INTERVAL)
    base = fit_model('edd_symmetric', GEOMETRY, cut_segments([drive], options.train_segments()))
    return drive, get_model('edd_symmetric').bind(base.values, GEOMETRY), options


def _keep_wheels(drive, keep):
    w = drive.wheels
    return replace(drive, wheels=WheelSamples(w.t_ns[keep], w.omega_l[keep], w.omega_r[keep]))


def _terms(drive, bound, options):
    samples = pose_samples([drive], bound, options)
    ranges = [0.0] * len(residual.range_names())
    for i, name in enumerate(residual.range_names()):
        ranges[i] = -2.0 if name.endswith('_lo') else 2.0
    return samples, window_terms([drive], samples, bound, options, ranges, options.smoothing_s)


def test_c262_poses_whose_window_the_model_does_not_integrate_are_left_out():
    """A 3 s gap in the wheel stamps, and ground truth that runs 5 s past the wheels' ends."""
    drive, bound, options = _setup()
    t = drive.wheels.t_ns
    # the half window less one pose spacing (10 Hz): every pose of such a window is beyond
    half = s_to_ns(options.smoothing_s - 0.1)
    gap = (t[0] + 20_000_000_000, t[0] + 23_000_000_000)
    careless = {
        'gap': (_keep_wheels(drive, (t < gap[0]) | (t > gap[1])), gap),
        'ends': (_keep_wheels(drive, (t > t[0] + 5e9) & (t < t[-1] - 5e9)), None)}
    clean_fit = fit_residual_model([drive], pose_samples([drive], bound, options), bound,
                                   options)
    assert clean_fit.levels[2] > 0   # the asymmetry is found on the clean drive
    for name, (wheels_cut, hole) in careless.items():
        samples, (target, valid, _, turning) = _terms(wheels_cut, bound, options)
        w = wheels_cut.wheels.t_ns
        if hole is None:
            outside = (samples.t_ns - half < w[0]) | (samples.t_ns + half > w[-1])
            far = (samples.t_ns - 2 * half > w[0]) & (samples.t_ns + 2 * half < w[-1])
        else:
            outside = (samples.t_ns + half > hole[0]) & (samples.t_ns - half < hole[1])
            far = (samples.t_ns + 2 * half < hole[0]) | (samples.t_ns - 2 * half > hole[1])
        assert outside.sum() > 10, name
        assert not valid[outside].any(), name   # the model stands still there: no model error
        # elsewhere the poses are kept, and the terms are finite
        assert np.isfinite(turning).all() and valid[far].mean() > 0.9, name
        fit = fit_residual_model([wheels_cut], samples, bound, options)
        assert fit.levels[2] > 0 and fit.inflation < 50.0, (name, fit.levels, fit.inflation)


def test_c263_the_traced_residuals_leave_out_the_same_poses(monkeypatch):
    """The residuals the tracing and the pose form read, on the same careless wheel stamps."""
    from skidkin_ros.core.calibration.diagnosis import regression
    from skidkin_ros.core.calibration.diagnosis.residuals import pose_residuals
    drive, bound, options = _setup()
    t = drive.wheels.t_ns
    cuts = ((t < t[0] + 20e9) | (t > t[0] + 23e9), (t > t[0] + 5e9) & (t < t[-1] - 5e9))
    clean_samples = pose_samples([drive], bound, options)
    _, clean_valid = pose_residuals([drive], clean_samples, bound, options)
    monkeypatch.setattr(regression, 'WINDOW_TERMS', False)
    for keep in cuts:
        careless = _keep_wheels(drive, keep)
        samples, (_, window_valid, _, _) = _terms(careless, bound, options)
        _, valid = pose_residuals([careless], samples, bound, options)
        assert np.array_equal(valid, window_valid)   # one rule for both
        assert valid.sum() < clean_valid.sum() - 10
        fit = fit_residual_model([careless], samples, bound, options)
        assert fit.levels[2] > 0 and fit.inflation < 50.0, (fit.levels, fit.inflation)
