"""Grounds remembered in a parameters file: online calibration's memory across a restart.

``~/save_calibration`` writes the active ground's parameters as the model's (``models.<m>.*``,
with their covariance) and every other ground online calibration remembers as the flat
``online.grounds.*`` parameters below, so the next start knows them. This module holds their
schema entries and the one check of their values (the node, ``skidkin predict`` and the saving
itself run it through :meth:`OdometryConfig.from_flat`); the learner takes them up in
:mod:`skidkin_ros.core.online.remembered`.

* ``online.grounds.model`` and ``online.grounds.parameter_names``: the model and the parameters
  (comma-separated, in the learner's order) the grounds are values of;
* ``online.grounds.parameters``: n x p values, row-major (one row per ground, in those units);
* ``online.grounds.covariance``: n p x p covariances, row-major, each symmetric positive
  definite (the ground's prior when it is taken back);
* ``online.grounds.learned_m``: the n grounds' metres of reference path learned on them.

n counts the grounds besides the active one: at most ``online.max_grounds`` - 1. All empty
(the default): no remembered ground, the learner starts as it always did.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Mapping

import numpy as np

from skidkin_ros.core.kinematics.augmented import AUGMENTED_NAME
from skidkin_ros.core.kinematics.extensions import get_extension, ordered
from skidkin_ros.core.kinematics.models import get_model
from skidkin_ros.core.kinematics.specs import check_value, Geometry
from skidkin_ros.errors import brief, ConfigError, ParameterError

__all__ = ['GROUND_NAMES', 'GROUND_LISTS', 'SavedGrounds', 'learned_names', 'ground_entries',
           'check_list', 'saved_grounds']

PREFIX = 'online.grounds.'
# The numeric lists (variable length: their kind is 'double_list').
GROUND_LISTS = ('online.grounds.parameters', 'online.grounds.covariance',
                'online.grounds.learned_m')
GROUND_NAMES = ('online.grounds.model', 'online.grounds.parameter_names') + GROUND_LISTS
WHAT_TO_DO = ('save the calibration again with this version, or delete the online.grounds.* '
              'entries to start without remembered grounds')


@dataclass(frozen=True)
class SavedGrounds:
    """The remembered grounds of a file: values (n, p), covariances (n, p, p), metres (n,)."""

    names: tuple[str, ...]
    values: np.ndarray
    covariance: np.ndarray
    learned_m: np.ndarray

    def __len__(self) -> int:
        return int(self.learned_m.size)


def ground_entries() -> list[tuple[str, str, Any, str]]:
    """Return (name, kind, default, description) of the online.grounds.* parameters."""
    return [
        ('online.grounds.model', 'string', '',
         'model whose parameters the remembered grounds hold (written by ~/save_calibration; '
         "must be the file's model)"),
        ('online.grounds.parameter_names', 'string', '',
         'their parameters, comma-separated, in the order of online.grounds.parameters'),
        ('online.grounds.parameters', 'double_list', [],
         'remembered grounds besides the active one (the model parameters): one row of '
         'parameter values per ground, row-major; empty: none (at most online.max_grounds - 1 '
         'rows)'),
        ('online.grounds.covariance', 'double_list', [],
         "each remembered ground's parameter covariance (p x p, row-major, positive "
         'definite), one after the other'),
        ('online.grounds.learned_m', 'double_list', [],
         'metres of reference path learned on each remembered ground [m]'),
    ]


def check_list(name: str, value: Any) -> list[float]:
    """Return a variable-length list of finite numbers (None, rcl's empty list: [])."""
    if value is None:
        return []
    if (not isinstance(value, (list, tuple))
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        raise ParameterError(f'parameter {name!r} must be a list of numbers, got {brief(value)}; '
                             + WHAT_TO_DO)
    numbers = [float(v) for v in value]
    bad = [v for v in numbers if not math.isfinite(v)]
    if bad:
        raise ParameterError(f'parameter {name!r} holds {len(bad)} non-finite value(s) '
                             f'({bad[0]}); every value of a remembered ground must be finite; '
                             + WHAT_TO_DO)
    return numbers


def learned_names(values: Mapping[str, Any]) -> tuple[str, ...]:
    """Return the parameters online calibration learns for the configured model, in order.

    A plain model: its parameters. An augmented model: its base model's, then
    ``<extension>.<parameter>`` for each fitted parameter of each extension, in the order the
    online learner lays them out (:func:`skidkin_ros.core.online.augmented.online_layout`).
    """
    if values['model'] != AUGMENTED_NAME:
        return get_model(values['model']).param_names
    names = list(get_model(values['augmented.base']).param_names)
    text = str(values['augmented.extensions'])
    for ext_name in ordered([p.strip() for p in text.replace(';', ',').split(',') if p.strip()]):
        ext = get_extension(ext_name)
        names += [f'{ext_name}.{p}' for p in ext.param_names if p in ext.fitted]
    return tuple(names)


def saved_grounds(values: Mapping[str, Any], geometry: Geometry) -> SavedGrounds | None:
    """Return the remembered grounds of validated values, or None; ConfigError where unfit.

    Checked: the model and parameter names are the learner's, the lists' lengths agree
    (n rows of p values, n p x p covariances, n metres), every value is within its
    parameter's range and constraints, every covariance symmetric positive definite, metres
    >= 0, and n + 1 (the active ground) <= online.max_grounds.
    """
    rows, flat_cov, metres = (values.get(name) or [] for name in GROUND_LISTS)
    model, text = values.get('online.grounds.model', ''), values.get(
        'online.grounds.parameter_names', '')
    if not (rows or flat_cov or metres or model or text):
        return None
    where = 'the remembered grounds (online.grounds.*)'
    if model != values['model']:
        raise ConfigError(
            f'{where} are parameters of model {model!r}, this file runs model '
            f'{values["model"]!r}; set model back to {model!r}, or delete the online.grounds.* '
            'entries to start without remembered grounds')
    names = tuple(part.strip() for part in str(text).split(',') if part.strip())
    expected = learned_names(values)
    if names != expected:
        raise ConfigError(
            f'{where} hold the parameters {list(names)}, online calibration of this model learns '
            f'{list(expected)}; ' + WHAT_TO_DO)
    p, n = len(names), len(metres)
    if n == 0 or len(rows) != n * p or len(flat_cov) != n * p * p:
        raise ConfigError(
            f'{where}: expected, for n grounds of the {p} parameters {list(names)}, '
            f'online.grounds.learned_m with n values (got {n}), online.grounds.parameters with '
            f'n x {p} (got {len(rows)}) and online.grounds.covariance with n x {p * p} (got '
            f'{len(flat_cov)}); ' + WHAT_TO_DO)
    limit = int(values['online.max_grounds'])
    if n + 1 > limit:
        raise ConfigError(
            f'{where}: {n} remembered grounds besides the active one, online.max_grounds '
            f'{limit} holds {limit - 1}; raise online.max_grounds to {n + 1} or more, or delete '
            'some grounds (a row of parameters, its covariance and its metres)')
    k = np.asarray(rows, dtype=float).reshape(n, p)
    cov = np.asarray(flat_cov, dtype=float).reshape(n, p, p)
    learned = np.asarray(metres, dtype=float)
    for i in range(n):
        label = f'remembered ground {i + 1} of {n} (online.grounds.*, row {i})'
        _check_values(values, geometry, names, k[i], label)
        if learned[i] < 0.0:
            raise ConfigError(f'{label}: learned_m {learned[i]:g} m is negative; expected the '
                              'metres learned on it (>= 0); ' + WHAT_TO_DO)
        c = cov[i]
        if not np.allclose(c, c.T, rtol=1e-6, atol=1e-15):
            raise ConfigError(f'{label}: its covariance is not symmetric; ' + WHAT_TO_DO)
        c = 0.5 * (c + c.T)
        eig = np.linalg.eigvalsh(c)
        if eig.min() <= 1e-12 * max(float(np.abs(eig).max()), 1e-300):
            raise ConfigError(
                f'{label}: its covariance is not positive definite (smallest eigenvalue '
                f'{eig.min():.3g}); a remembered ground needs an uncertainty in every '
                'direction; ' + WHAT_TO_DO)
        cov[i] = c
    return SavedGrounds(names, k, cov, learned)


def _check_values(values: Mapping[str, Any], geometry: Geometry, names: tuple[str, ...],
                  k: np.ndarray, label: str) -> None:
    """Refuse a ground's values outside their parameters' ranges or constraints."""
    base_name = (values['augmented.base'] if values['model'] == AUGMENTED_NAME
                 else values['model'])
    base = get_model(base_name)
    size = len(base.params)
    try:
        base.vector(dict(zip(names[:size], k[:size])), geometry)
        for name, value in zip(names[size:], k[size:]):
            ext_name, pname = name.split('.', 1)
            spec = next(s for s in get_extension(ext_name).params if s.name == pname)
            check_value(spec, float(value), f'augmented.{ext_name}.')
    except ParameterError as err:
        raise ConfigError(f'{label}: {err}; ' + WHAT_TO_DO) from err
