"""A paired layout's twist and exact gradient on the second columns only: the pairs' numbers."""

import numpy as np
import pytest
from skidkin_ros.core.calibration.engine import ParameterLayout
from skidkin_ros.core.kinematics import residual
from skidkin_ros.core.kinematics.augmented_tangents import interval_tangents
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.online.augmented import _pair_steps, LayoutModel

GEOMETRY = Geometry(0.165, 0.555)
BASE = {'alpha_l': 0.93, 'alpha_r': 0.88, 'x_v': 0.04, 'y_l': 0.41, 'y_r': -0.37}


def _residual(rng):
    names = residual.coefficient_names()
    values = {name: float(v) for name, v in zip(names, rng.normal(0.0, 0.2, len(names)))}
    for name, _, _ in residual.INPUTS:
        values[f'{name}_lo'], values[f'{name}_hi'] = -3.0, 2.5
    values.update(level=7.0, gain_vx=1.1, gain_vy=0.9, gain_wz=1.2)
    return values


@pytest.mark.parametrize('extensions', [('residual_model',),
                                        ('speed_slip', 'acceleration_slip'),
                                        ('lateral_skid', 'acceleration_slip', 'residual_model')])
def test_the_second_columns_give_the_pair_intervals_numbers(extensions):
    rng = np.random.default_rng(len(extensions))
    values = {'speed_slip': {'k': 0.1}, 'acceleration_slip': {'tau_s': 0.05},
              'lateral_skid': {'k': 0.03}, 'residual_model': _residual(rng)}
    free = {name: ('gain_vx', 'gain_vy', 'gain_wz') if name == 'residual_model'
            else ('k' if name != 'acceleration_slip' else 'tau_s',) for name in extensions}
    model = LayoutModel(ParameterLayout.build('edd_asymmetric', GEOMETRY, BASE,
                                              {n: values[n] for n in extensions}, extensions,
                                              True, free))
    assert model.paired
    # an odd width too: a stack of segments pads, and a lone last column has no twist
    for width in (400, 401):
        _compare(model, rng.uniform(-8.0, 8.0, (3, width)), rng.uniform(-8.0, 8.0, (3, width)))


def _compare(model, left, right):
    k = model.layout.vector()
    # the forms over every column of the pairs (what these replaced)
    still, dt_s, restart = _pair_steps(left.shape)
    bound = model.source(k)
    twist = bound.intervals(still, left, right, dt_s, restart)[1].copy()
    twist[:, ::2] = 0.0
    _, tangents = interval_tangents(bound, still, left, right, dt_s, restart, model.layout.free)
    gradient = np.moveaxis(np.stack(tangents), (0, 1), (-2, -1)).copy()
    gradient[:, ::2] = 0.0
    np.testing.assert_array_equal(model.twist(k, GEOMETRY, left, right), twist)
    np.testing.assert_array_equal(model.twist_gradient(k, GEOMETRY, left, right), gradient)
    assert np.any(gradient[:, 1::2] != 0.0) and np.any(twist[:, 1::2] != 0.0)
