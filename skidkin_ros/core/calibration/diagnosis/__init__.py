"""Diagnose what a calibrated model misses, add it as extensions, measure before and after.

``diagnose(train, evaluate, geometry, base_values_by_model, base_model_name, options)``
(:mod:`.recipe`):

1. **Residuals** (:mod:`.residuals`). Ground-truth body velocities come from a smoothing
   differentiator on the fresh ground-truth poses only (sample-and-hold duplicates dropped); the
   model's poses at the same stamps go through the same differentiator, so both are smoothed
   alike. Residual = ground truth - model, per pose, in the body frame (v_x, v_y, omega); and per
   training segment, the end-pose error.
2. **Trace** (:mod:`.tracing`). The residuals are correlated with every signal the data offers
   (wheel speeds, sum, difference, ratio, their time derivatives, body speed, yaw rate,
   curvature, v omega, direction, time in drive, position, IMU yaw rate) and the
   wheel-vs-ground-truth lag is found by running the model over a range of time offsets.
3. **Candidates** (:mod:`.base`, :mod:`.candidates`, :mod:`.state`, :mod:`.regression`,
   :mod:`.sparse`). The base model is questioned first (the other models, cross-validated; one
   that passes replaces it unless the given one with its extensions ends more than
   ``min_relative_gain`` lower in held-out loss than it with its own). Every named extension
   (and, when none explains the rest, the data-driven residual model: Bayesian linear
   regression of the per-pose residuals on a library of smooth terms of the wheel-speed state,
   its level chosen on held-out likelihood; by name, the older sparse fallback, STLSQ) is
   fitted on segments by the one least-squares engine
   (:mod:`skidkin_ros.core.calibration.engine`, as calibration fits), with the base model's
   parameters refitted jointly (``refit_base``; the file then holds the joint values for the
   base model). Each extension's registry entry gives its start values, grid-searched
   parameters and complexity. With ``trim`` the outlier training segments of the base refit are
   dropped once, as calibration does; off by default, because the segments a missing effect
   hits hardest look like outliers to the base model (a yaw slip at one speed ratio, fast
   driving) and trimming them hides the effect.
4. **Selection** (:mod:`.select_extensions`). Cross-validation over ``folds`` groups of training
   segments: each candidate's held-out loss (whitened squared end-pose error) against the
   current model's. Parsimony: a candidate is accepted only when it lowers the held-out loss by
   more than ``min_relative_gain`` AND a one-sided Wilcoxon signed-rank test of the per-segment
   differences gives p < ``significance``. Greedy forward selection, at most
   ``max_extensions``; the sparse fallback is tried only when no named extension passes. The
   fits of a round are independent tasks, run on ``jobs`` processes.
5. **Before/after** (:mod:`.results`). eps_t and eps_theta on the evaluation drives (a
   deterministic hold-out when none are given) for the base model as given, refitted, and after
   each accepted extension; text lines and the parameters file from the result.
"""

from skidkin_ros.core.calibration.diagnosis.options import DiagnosisOptions
from skidkin_ros.core.calibration.diagnosis.recipe import diagnose
from skidkin_ros.core.calibration.diagnosis.residuals import (body_velocities, COMPONENTS,
                                                              truth_velocities)
from skidkin_ros.core.calibration.diagnosis.results import DiagnosisResult, ModelStep
from skidkin_ros.core.calibration.diagnosis.select_extensions import CandidateScore, Progress
from skidkin_ros.core.calibration.diagnosis.sparse import stlsq
from skidkin_ros.core.calibration.diagnosis.state import ModelState
from skidkin_ros.core.calibration.diagnosis.tracing import Trace

__all__ = ['DiagnosisOptions', 'DiagnosisResult', 'CandidateScore', 'ModelStep', 'ModelState',
           'Trace', 'Progress', 'COMPONENTS', 'diagnose', 'truth_velocities', 'body_velocities',
           'stlsq']
