"""One diagnosis's outcome as a JSON line, to check that a code change keeps the results.

``python lab/bench/diag_same.py husky`` (the Husky windows, even calib_step train, odd
evaluate, the residual model as candidate) or
``python lab/bench/diag_same.py acceleration_slip+lateral_skid`` (a case of the effects study:
two simulated training drives with those effects, three for evaluation, every candidate). Run
it with this checkout and with an older one (``PYTHONPATH=OLDER python
lab/bench/diag_same.py ...``) and compare: the extensions found, the
base and extension values, eps_t and eps_theta of every step; ``se`` gives the standard errors
of the final model's fitted parameters on the training segments (from the exact Jacobian, when
the code has one), to judge a difference of values. ``FD=1`` in the environment makes this
checkout's fits use finite-difference Jacobians.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import sys
import time

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def _inputs(case: str):
    from skidkin_ros.core.calibration.diagnosis import DiagnosisOptions
    from skidkin_ros.core.calibration.fitting import fit_model
    from skidkin_ros.core.calibration.segments import cut_segments
    if case == 'husky':
        from skidkin_ros.adapters.table import read_table
        from skidkin_ros.core.calibration.holdout import split_holdout
        from skidkin_ros.core.kinematics.specs import Geometry
        geometry = Geometry(0.1651, 0.555)
        table = read_table(ROOT / 'data' / 'husky' / 'drive_husky_windows.csv')
        train, evaluate = split_holdout(table, every=2, key='calib_step')
        options = DiagnosisOptions(candidates=('residual_model',), interval='ending',
                                   question_base=False)
    else:
        sys.path.insert(0, str(ROOT))
        from lab.studies import effects
        geometry = effects.GEOMETRY
        chosen = effects.case_effects(case)
        train = effects.sim_drives(chosen, [1, 2], 120.0)
        evaluate = effects.sim_drives(chosen, [3, 4, 5], 120.0)
        options = DiagnosisOptions(interval=effects.SIM_INTERVAL)
    base = fit_model('edd_symmetric', geometry, cut_segments(train, options.train_segments()))
    return train, evaluate, geometry, {'edd_symmetric': base.values}, options


def _standard_errors(result, train, geometry, options) -> dict[str, float]:
    """Return s (J^T J)^-1/2 of the final model's fitted parameters on all training segments."""
    from skidkin_ros.core.calibration.diagnosis.state import layout_of
    from skidkin_ros.core.calibration.predictor import SegmentPredictor
    from skidkin_ros.core.calibration.segments import cut_segments
    from skidkin_ros.core.kinematics.extensions import get_extension
    from skidkin_ros.core.kinematics.models import get_model
    predictor = SegmentPredictor(train, cut_segments(train, options.train_segments()),
                                 options.max_dt_s, options.interval)
    layout = layout_of(result.base_model, geometry, result.final, True)
    vector = layout.vector()
    timing = [c for c, (i, _) in enumerate(layout.free)
              if i >= 0 and get_extension(layout.extensions[i]).stage == 'timing']
    jac = predictor.errors_jacobian(layout.source(vector), layout.free,
                                    timing[0] if timing else None)
    jac = (jac * options.whitening[None, :, None]).reshape(-1, vector.size)
    white = (predictor.errors(layout.source(vector)) * options.whitening).ravel()
    s2 = white @ white / max(white.size - vector.size, 1)
    se = np.sqrt(np.diag(np.linalg.pinv(jac.T @ jac)) * s2)
    names = [f'base.{get_model(result.base_model).param_names[j]}' if i < 0 else
             f'{layout.extensions[i]}.{get_extension(layout.extensions[i]).param_names[j]}'
             for i, j in layout.free]
    return {name: float(value) for name, value in zip(names, se)}


def main() -> int:
    case = sys.argv[1] if len(sys.argv) > 1 else 'husky'
    if os.environ.get('FD'):
        from skidkin_ros.core.calibration.diagnosis import state
        state.ANALYTIC_JACOBIAN = False
    from skidkin_ros.core.calibration.diagnosis import diagnose
    train, evaluate, geometry, base_values, options = _inputs(case)
    tic = time.process_time()
    result = diagnose(train, evaluate, geometry, base_values, 'edd_symmetric', options, jobs=1)
    final = result.final
    out = {'cpu_s': time.process_time() - tic, 'found': list(result.extensions),
           'base_model': result.base_model, 'base_values': final.base_values,
           'ext_values': {name: final.ext_values[name] for name in result.extensions},
           'steps': [(step.label, step.stats_t.median, step.stats_theta.median)
                     for step in result.steps]}
    try:
        out['se'] = _standard_errors(result, train, geometry, options)
    except AttributeError as err:  # an older checkout without the exact Jacobian
        out['se_error'] = repr(err)
    sys.stdout.write(json.dumps(out) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
