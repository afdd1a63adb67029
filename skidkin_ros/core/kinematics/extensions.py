"""Named extensions of a kinematic model: what a linear wheel-to-body map misses.

An augmented model is a base model (any of the five, with its parameters) followed by a list of
extensions. Each extension has its own parameter specs (name, unit, default, bounds,
description), a formula, the signal that reveals it in the residuals, and acts at one stage:

- ``timing``: the true motion lags the wheel stamps by an offset (``time_offset``): poses are
  published at sample stamp + offset, and a segment [t_a, t_b] of ground truth is predicted from
  the wheel samples of [t_a - offset, t_b - offset];
- ``wheels``: the wheels' own speeds differ from the encoders' through a state the drive's
  history sets (``backlash``: the play a motor turns through after a reversal before its wheel
  moves, :mod:`~skidkin_ros.core.kinematics.backlash`), applied first;
- ``twist``: a change of the body twist (v_x, v_y, omega) given the wheel speeds, the time since
  the drive started and the base twist's rate of change (its backward difference over one wheel
  sample: acceleration slip, the sparse fallback's derivative terms); slips, skid, direction,
  terrain;
- ``dynamics``: the body twist follows the twist of the previous stages through a first-order
  response, on every component (``first_order_lag``) or on some (``forward_lag``, ``yaw_lag``,
  ``component_lags``), applied last. At most one of them (they share the ``group`` 'lag').

Every extension with default parameters leaves the base model unchanged (the neutral value),
so an augmented model with defaults predicts exactly what its base model predicts.

One registry entry per extension feeds everything, as a ParamSpec does for a parameter: the
integrator (stage, formula), the parameters file (specs), and the diagnosis, which reads from
the entry how to fit it (which parameters, their start values from what the trace measured
(:class:`FitHints`), which are searched on a grid and over what range), how simple it is (the
simpler of two equally good explanations is kept), which simpler extension it cannot be told
from at short time scales, and which residual plot shows it. Adding an extension is adding an
entry to ``_ALL`` (and its formula), not editing the diagnosis. The sparse fallback's library of
twist terms is a registry too (``LIBRARY``, in :mod:`~skidkin_ros.core.kinematics.sparse_library`
with the bound on a data-driven correction; re-exported here): a new term is one
:class:`LibraryTerm`.

This module stays whole: it is the registry and the formulas its entries name, and each formula
sits beside its scalar twin, which must do the same operations in the same order so that the
node and the batch prediction agree, and beside its exact derivatives (``_<name>_partials``,
:meth:`Extension.partials`: what the fits' analytic Jacobians are made of; a change of a rule is
a change of its derivatives, which ``test_jacobians.py`` checks against finite differences);
moving the families elsewhere would spread one entry over several modules.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Callable, Mapping, Sequence

import numpy as np

from skidkin_ros.core.kinematics import residual
from skidkin_ros.core.kinematics.sparse_library import (bounded_correction, LIBRARY,
                                                        LibraryTerm, SLIP_LEVER_M, SPARSE_FEATURES,
                                                        sparse_features, sparse_gradients,
                                                        SPARSE_OUTPUTS, speeding_up)
from skidkin_ros.core.kinematics.specs import check_value, ParamSpec
from skidkin_ros.errors import ParameterError

__all__ = [
    'FitHints',
    'Extension',
    'EXTENSIONS',
    'EXTENSION_NAMES',
    'LibraryTerm',
    'LIBRARY',
    'SLIP_LEVER_M',
    'SPARSE_FEATURES',
    'SPARSE_OUTPUTS',
    'bounded_correction',
    'residual_jacobian',
    'get_extension',
    'ordered',
    'ratio_bump',
    'sparse_features',
    'speeding_up',
]

# Never remove more than this fraction of the forward speed (keeps v_x's sign).
MAX_SPEED_SLIP = 0.8


@dataclass(frozen=True)
class FitHints:
    """What the data say before an extension is fitted: for its start values and scan range.

    ``lag_s``: the wheel -> ground-truth lag the trace found beyond the stamp convention (s);
    ``convention_s``: the stamp convention's time offset (s, -dt/2 or 0); ``period_s``: the
    median wheel sample period (s); ``duration_s``: the longest training drive (s).
    """

    lag_s: float = 0.0
    convention_s: float = 0.0
    period_s: float = 0.0
    duration_s: float = 0.0


@dataclass(frozen=True)
class Extension:
    """One named extension: specs, stage, formula, and how a diagnosis fits and reports it.

    ``fitted`` names the parameters a diagnosis fits (the others keep their value, e.g. a blend
    width); ``start`` gives start values better than the neutral defaults from the
    :class:`FitHints`. ``scan`` names parameters first searched on a grid over
    ``scan_range(hints)`` (step-like effects), and ``refine`` says whether they are then refined
    by least squares. ``library``: the parameters are coefficients of library terms, the terms
    chosen by sparse regression (only those are fitted). ``regression``: the coefficients of a
    data-driven residual model, fitted in closed form by Bayesian linear regression on the
    per-pose residuals, its terms and level chosen on held-out likelihood (none is fitted by
    least squares). ``group``: extensions of one group
    exclude each other (one lag per model). ``lags``: for a dynamics extension, the parameter
    giving the time constant of each twist component (v_x, v_y, omega), None: not lagged.
    ``short_alias`` = (parameter, other
    extension): with that parameter no longer than one wheel sample period this extension cannot
    be told from the other one, which the selection keeps. ``residual_view`` = (residual
    component, trace signal, fold by the component's direction): the plot that shows the effect.
    """

    name: str
    title: str
    stage: str
    formula: str
    signal: str
    params: tuple[ParamSpec, ...]
    fitted: tuple[str, ...]
    scan: tuple[str, ...] = ()
    refine: bool = True
    start: Callable[[FitHints], dict[str, float]] | None = None
    scan_range: Callable[[FitHints], tuple[float, float]] | None = None
    library: bool = False
    short_alias: tuple[str, str] | None = None
    residual_view: tuple[str, str, bool] = ('v_x', 'body_speed', False)
    group: str = ''
    lags: tuple[str | None, str | None, str | None] = (None, None, None)
    regression: bool = False

    @property
    def learned(self) -> bool:
        """Whether the data choose its terms (a library or a regression extension)."""
        return self.library or self.regression

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(spec.name for spec in self.params)

    def defaults(self) -> dict[str, float]:
        return {spec.name: spec.default_for(None) for spec in self.params}

    def start_values(self, hints: FitHints) -> dict[str, float]:
        """Return every parameter's start value: the defaults, then ``start(hints)``."""
        values = self.defaults()
        if self.start is not None:
            values.update(self.start(hints))
        return values

    def complexity(self, terms: Sequence[str] = ()) -> tuple[int, int]:
        """Return (parameters it fits, 1 if it carries state): the simpler sorts first.

        ``terms``: the library terms chosen (a library extension counts those).
        """
        count = len(terms) if self.learned else len(self.fitted) + len(self.scan)
        return count, int(self.stage in ('dynamics', 'wheels'))

    def vector(self, values: Mapping[str, float], prefix: str = '') -> np.ndarray:
        """Return the parameter vector in spec order; missing values take their defaults."""
        unknown = sorted(set(values) - set(self.param_names))
        if unknown:
            raise ParameterError(f'extension {self.name!r} has no parameter(s) {unknown}; its '
                                 f'parameters are {list(self.param_names)}')
        merged = {**self.defaults(), **values}
        prefix = prefix or f'augmented.{self.name}.'
        return np.array([check_value(spec, merged[spec.name], prefix) for spec in self.params])

    def mapping(self, k: Sequence[float]) -> dict[str, float]:
        return {name: float(value) for name, value in zip(self.param_names, k)}

    def apply(self, k: np.ndarray, twist: np.ndarray, omega_l: np.ndarray,
              omega_r: np.ndarray, t_s: np.ndarray, rate: np.ndarray | None = None
              ) -> np.ndarray:
        """Return the twist (..., 3) after this extension (twist stage; identity otherwise).

        ``rate``: the base twist's rate of change (..., 3) (None: zero, a steady state).
        """
        if self.stage != 'twist':
            return twist
        if rate is None:
            rate = np.zeros(np.shape(twist))
        return _TWIST_FUNCTIONS[self.name](k, twist, omega_l, omega_r, t_s, rate)

    def partials(self, k: np.ndarray, twist: np.ndarray, omega_l: np.ndarray,
                 omega_r: np.ndarray, t_s: np.ndarray, rate: np.ndarray,
                 wanted: Sequence[int] | None = None, inputs: bool = True
                 ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray]:
        """Return :meth:`apply`'s exact derivatives at these inputs (twist stage).

        (d out / d twist (..., 3, 3), d out / d rate (..., 3, 3), d out / d k (..., 3, n)):
        None stands for the identity (twist) or zero (rate); every stage but the twist stage
        returns (None, None, zeros). ``wanted``: the indices of the parameters whose slopes are
        returned, in that order (default: all); ``inputs=False``: the caller carries no
        tangent in, so the slopes by twist and rate are left out (None, None). Where a rule
        switches branch (a clamp, a bound) the derivative is the branch's at that point, as a
        one-sided difference would see it.
        """
        wanted = list(range(len(self.params))) if wanted is None else list(wanted)
        if self.stage != 'twist':
            return None, None, np.zeros(np.shape(twist) + (len(wanted),))
        function = _PARTIAL_FUNCTIONS[self.name]
        args = (np.asarray(k, dtype=float), np.asarray(twist, dtype=float), omega_l, omega_r,
                t_s, np.asarray(rate, dtype=float))
        if self.learned:  # hundreds of coefficients: only the wanted ones are computed
            d_twist, d_rate, d_k = function(*args, wanted=wanted, inputs=inputs)
        else:
            d_twist, d_rate, d_k = function(*args)
            d_k = d_k[..., wanted]
        return (d_twist, d_rate, d_k) if inputs else (None, None, d_k)

    @property
    def uses_rate(self) -> bool:
        """Whether its twist rule reads the base twist's rate of change."""
        return self.name in _USES_RATE

    def time_constants(self, k: Sequence[float]) -> tuple[float, float, float]:
        """Return the lag time constant (s) of each twist component, 0 where not lagged."""
        values = self.mapping(k)
        return tuple(0.0 if name is None else values[name] for name in self.lags)

    def scalar_apply(self) -> Callable[..., tuple[float, float, float]] | None:
        """Return this extension on plain floats, or None if it has no such form.

        The function takes ``(k, vx, vy, wz, omega_l, omega_r, t_s, rate)`` (``k`` and ``rate``
        tuples of floats) and returns the new (vx, vy, wz): :meth:`apply`'s operations in its
        order, so the node's per-sample path equals the batch form bit for bit. Stages other
        than the twist stage return the twist unchanged.
        """
        if self.stage != 'twist':
            return _scalar_identity
        return _SCALAR_FUNCTIONS.get(self.name)


def _spec(name: str, unit: str, default: float, lower: float, upper: float,
          text: str) -> ParamSpec:
    return ParamSpec(name, unit, default, lower, upper, text)


def ratio_bump(omega_l: np.ndarray, omega_r: np.ndarray, peak: float,
               width: float) -> np.ndarray:
    """Return a bump in [0, 1] around a slow/fast wheel-speed ratio ``peak`` (same sign only)."""
    big = np.maximum(np.abs(omega_l), np.abs(omega_r))
    small = np.minimum(np.abs(omega_l), np.abs(omega_r))
    same_sign = (omega_l * omega_r) > 0.0
    ratio = np.where(same_sign & (big > 0.0), small / np.where(big > 0.0, big, 1.0), -1.0)
    return np.exp(-((ratio - peak) / width) ** 2)


def _speed_slip(k, twist, omega_l, omega_r, t_s, rate):
    out = np.array(twist, dtype=float, copy=True)
    v_x = out[..., 0]
    out[..., 0] = v_x * (1.0 - np.minimum(k[0] * np.abs(v_x), MAX_SPEED_SLIP))
    return out


def _direction_asymmetry(k, twist, omega_l, omega_r, t_s, rate):
    out = np.array(twist, dtype=float, copy=True)
    v_x = out[..., 0]
    reverse = np.clip(-v_x / k[1], 0.0, 1.0)
    out[..., 0] = v_x * (1.0 - k[0] * reverse)
    return out


def _lateral_skid(k, twist, omega_l, omega_r, t_s, rate):
    out = np.array(twist, dtype=float, copy=True)
    out[..., 1] = out[..., 1] + k[0] * out[..., 0] * out[..., 2]
    return out


def _icr_offset(k, twist, omega_l, omega_r, t_s, rate):
    out = np.array(twist, dtype=float, copy=True)
    out[..., 1] = out[..., 1] + k[0] * out[..., 2]
    return out


def _ratio_yaw_slip(k, twist, omega_l, omega_r, t_s, rate):
    out = np.array(twist, dtype=float, copy=True)
    bump = ratio_bump(np.asarray(omega_l, float), np.asarray(omega_r, float), k[1], k[2])
    out[..., 2] = out[..., 2] * (1.0 - k[0] * bump)
    return out


def _terrain_regime(k, twist, omega_l, omega_r, t_s, rate):
    out = np.array(twist, dtype=float, copy=True)
    scale = np.where(np.asarray(t_s) >= k[1], 1.0 - k[0], 1.0)
    out[..., 0] = out[..., 0] * scale
    out[..., 2] = out[..., 2] * scale
    return out


def _acceleration_slip(k, twist, omega_l, omega_r, t_s, rate):
    out = np.array(twist, dtype=float, copy=True)
    v_x = out[..., 0]
    dv = np.asarray(rate, dtype=float)[..., 0]
    loss = np.minimum(k[0] * np.abs(speeding_up(v_x, dv)), np.abs(v_x))
    out[..., 0] = v_x - np.copysign(loss, v_x)
    return out


# Their exact derivatives (Extension.partials): (d out/d twist, d out/d rate, d out/d k), next to
# each rule so that a change of a rule and of its derivative is one edit. test_extensions checks
# every entry against finite differences.
def _eye(twist: np.ndarray) -> np.ndarray:
    return np.broadcast_to(np.eye(3), np.shape(twist) + (3,)).copy()


def _speed_slip_partials(k, twist, omega_l, omega_r, t_s, rate):
    v_x = twist[..., 0]
    inside = k[0] * np.abs(v_x) < MAX_SPEED_SLIP
    d_twist = _eye(twist)
    d_twist[..., 0, 0] = np.where(inside, 1.0 - 2.0 * k[0] * np.abs(v_x), 1.0 - MAX_SPEED_SLIP)
    d_k = np.zeros(np.shape(twist) + (1,))
    d_k[..., 0, 0] = np.where(inside, -v_x * np.abs(v_x), 0.0)
    return d_twist, None, d_k


def _direction_asymmetry_partials(k, twist, omega_l, omega_r, t_s, rate):
    v_x = twist[..., 0]
    ratio = -v_x / k[1]
    reverse = np.clip(ratio, 0.0, 1.0)
    inside = (ratio > 0.0) & (ratio < 1.0)
    d_twist = _eye(twist)
    d_twist[..., 0, 0] = 1.0 - k[0] * reverse + np.where(inside, v_x * k[0] / k[1], 0.0)
    d_k = np.zeros(np.shape(twist) + (2,))
    d_k[..., 0, 0] = -v_x * reverse
    d_k[..., 0, 1] = np.where(inside, -v_x * k[0] * v_x / k[1] ** 2, 0.0)
    return d_twist, None, d_k


def _lateral_skid_partials(k, twist, omega_l, omega_r, t_s, rate):
    d_twist = _eye(twist)
    d_twist[..., 1, 0] = k[0] * twist[..., 2]
    d_twist[..., 1, 2] = k[0] * twist[..., 0]
    d_k = np.zeros(np.shape(twist) + (1,))
    d_k[..., 1, 0] = twist[..., 0] * twist[..., 2]
    return d_twist, None, d_k


def _icr_offset_partials(k, twist, omega_l, omega_r, t_s, rate):
    d_twist = _eye(twist)
    d_twist[..., 1, 2] = k[0]
    d_k = np.zeros(np.shape(twist) + (1,))
    d_k[..., 1, 0] = twist[..., 2]
    return d_twist, None, d_k


def _ratio_yaw_slip_partials(k, twist, omega_l, omega_r, t_s, rate):
    omega_l = np.asarray(omega_l, float)
    omega_r = np.asarray(omega_r, float)
    bump = np.broadcast_to(ratio_bump(omega_l, omega_r, k[1], k[2]), twist.shape[:-1])
    big = np.maximum(np.abs(omega_l), np.abs(omega_r))
    small = np.minimum(np.abs(omega_l), np.abs(omega_r))
    ratio = np.where(((omega_l * omega_r) > 0.0) & (big > 0.0),
                     small / np.where(big > 0.0, big, 1.0), -1.0)
    q = (ratio - k[1]) / k[2]
    w = twist[..., 2]
    d_twist = _eye(twist)
    d_twist[..., 2, 2] = 1.0 - k[0] * bump
    d_k = np.zeros(np.shape(twist) + (3,))
    d_k[..., 2, 0] = -w * bump
    d_k[..., 2, 1] = -w * k[0] * bump * 2.0 * q / k[2]
    d_k[..., 2, 2] = -w * k[0] * bump * 2.0 * q * q / k[2]
    return d_twist, None, d_k


def _terrain_regime_partials(k, twist, omega_l, omega_r, t_s, rate):
    after = np.broadcast_to(np.asarray(t_s) >= k[1], twist.shape[:-1])
    scale = np.where(after, 1.0 - k[0], 1.0)
    d_twist = _eye(twist)
    d_twist[..., 0, 0] = scale
    d_twist[..., 2, 2] = scale
    d_k = np.zeros(np.shape(twist) + (2,))  # the switch is a step: no slope (grid-searched)
    d_k[..., 0, 0] = np.where(after, -twist[..., 0], 0.0)
    d_k[..., 2, 0] = np.where(after, -twist[..., 2], 0.0)
    return d_twist, None, d_k


def _acceleration_slip_partials(k, twist, omega_l, omega_r, t_s, rate):
    v_x = twist[..., 0]
    up = speeding_up(v_x, rate[..., 0])
    slipping = k[0] * np.abs(up) < np.abs(v_x)
    sign = np.copysign(1.0, v_x)
    d_twist = _eye(twist)
    d_twist[..., 0, 0] = np.where(slipping, 1.0, 0.0)
    d_rate = np.zeros(np.shape(twist) + (3,))
    # speeding up: sign(dv) = sign(v_x), so v_x - sign(v_x) k |dv| = v_x - k dv
    d_rate[..., 0, 0] = np.where(slipping & (up != 0.0), -k[0], 0.0)
    d_k = np.zeros(np.shape(twist) + (1,))
    d_k[..., 0, 0] = np.where(slipping, -sign * np.abs(up), 0.0)
    return d_twist, d_rate, d_k


def _bounded_partials(twist: np.ndarray, change: np.ndarray, d_change_twist: np.ndarray,
                      d_change_rate: np.ndarray, d_change_k: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the derivatives of :func:`bounded_correction` (twist + change, clipped).

    ``d_change_*``: the change's derivatives (..., 3, 3) and (..., 3, n); a clipped component
    follows the bound instead (|v| + L |w| or |w| + |v| / L).
    """
    v, w = twist[..., 0], twist[..., 2]
    linear = np.abs(v) + np.abs(w) * SLIP_LEVER_M
    angular = np.abs(w) + np.abs(v) / SLIP_LEVER_M
    bound = np.stack([linear, linear, angular], axis=-1)
    side = np.where(change > bound, 1.0, np.where(change < -bound, -1.0, 0.0))
    free = (side == 0.0)[..., None]
    d_bound = np.zeros(np.shape(twist) + (3,))
    sv, sw = np.sign(v), np.sign(w)
    d_bound[..., 0, 0] = d_bound[..., 1, 0] = sv
    d_bound[..., 0, 2] = d_bound[..., 1, 2] = sw * SLIP_LEVER_M
    d_bound[..., 2, 0] = sv / SLIP_LEVER_M
    d_bound[..., 2, 2] = sw
    d_twist = _eye(twist) + np.where(free, d_change_twist, side[..., None] * d_bound)
    d_rate = np.where(free, d_change_rate, 0.0)
    d_k = np.where(free, d_change_k, 0.0)
    return d_twist, d_rate, d_k


# The same functions on plain floats (one sample): the node runs these once per wheel sample.
# numpy's exp (not math's) where the array forms use it: libm may differ by an ulp.
def _scalar_identity(k, vx, vy, w, omega_l, omega_r, t_s, rate):
    return vx, vy, w


def _scalar_speed_slip(k, vx, vy, w, omega_l, omega_r, t_s, rate):
    return vx * (1.0 - min(k[0] * abs(vx), MAX_SPEED_SLIP)), vy, w


def _scalar_direction_asymmetry(k, vx, vy, w, omega_l, omega_r, t_s, rate):
    reverse = min(max(-vx / k[1], 0.0), 1.0)
    return vx * (1.0 - k[0] * reverse), vy, w


def _scalar_lateral_skid(k, vx, vy, w, omega_l, omega_r, t_s, rate):
    return vx, vy + k[0] * vx * w, w


def _scalar_icr_offset(k, vx, vy, w, omega_l, omega_r, t_s, rate):
    return vx, vy + k[0] * w, w


def _scalar_ratio_yaw_slip(k, vx, vy, w, omega_l, omega_r, t_s, rate):
    big = max(abs(omega_l), abs(omega_r))
    small = min(abs(omega_l), abs(omega_r))
    ratio = small / big if (omega_l * omega_r) > 0.0 and big > 0.0 else -1.0
    q = (ratio - k[1]) / k[2]
    bump = float(np.exp(-(q * q)))
    return vx, vy, w * (1.0 - k[0] * bump)


def _scalar_terrain_regime(k, vx, vy, w, omega_l, omega_r, t_s, rate):
    scale = 1.0 - k[0] if t_s >= k[1] else 1.0
    return vx * scale, vy, w * scale


def _scalar_acceleration_slip(k, vx, vy, w, omega_l, omega_r, t_s, rate):
    dv = rate[0]
    loss = min(k[0] * abs(dv), abs(vx)) if vx * dv > 0.0 else 0.0
    return vx - math.copysign(loss, vx), vy, w


def _sparse_correction(k, twist, omega_l, omega_r, t_s, rate):
    features = sparse_features(twist, rate)
    coef = np.asarray(k, dtype=float).reshape(len(SPARSE_OUTPUTS), len(SPARSE_FEATURES))
    return bounded_correction(twist, features @ coef.T)


def _sparse_correction_partials(k, twist, omega_l, omega_r, t_s, rate, wanted, inputs):
    features = sparse_features(twist, rate)
    coef = np.asarray(k, dtype=float).reshape(len(SPARSE_OUTPUTS), len(SPARSE_FEATURES))
    d_change_twist = np.zeros(np.shape(twist) + (3,))
    d_change_rate = np.zeros(np.shape(twist) + (3,))
    if inputs:
        grads = sparse_gradients(twist, rate)  # (..., F, 4): d term / d (v, w, dv, dw)
        d_inputs = np.einsum('of,...fi->...oi', coef, grads)  # (..., 3, 4)
        d_change_twist[..., 0], d_change_twist[..., 2] = d_inputs[..., 0], d_inputs[..., 1]
        d_change_rate[..., 0], d_change_rate[..., 2] = d_inputs[..., 2], d_inputs[..., 3]
    count = len(SPARSE_FEATURES)
    d_change_k = np.zeros(np.shape(twist) + (len(wanted),))
    for c, j in enumerate(wanted):
        d_change_k[..., j // count, c] = features[..., j % count]
    return _bounded_partials(twist, features @ coef.T, d_change_twist, d_change_rate,
                             d_change_k)


def _sparse_specs() -> tuple[ParamSpec, ...]:
    specs = []
    for out_name, out_unit in SPARSE_OUTPUTS:
        for feat_name, feat_unit in SPARSE_FEATURES:
            specs.append(_spec(f'{out_name}_{feat_name}', f'({out_unit})/({feat_unit})', 0.0,
                               -10.0, 10.0, f'{out_name} correction per {feat_name}'))
    return tuple(specs)


_RESIDUAL_COEFS = len(residual.coefficient_names())
_RESIDUAL_RANGES = len(residual.range_names())


_RESIDUAL_GAINS = _RESIDUAL_COEFS + _RESIDUAL_RANGES + 1  # after the level


def _residual_model(k, twist, omega_l, omega_r, t_s, rate):
    k = np.asarray(k, dtype=float)
    ranges = k[_RESIDUAL_COEFS:_RESIDUAL_COEFS + _RESIDUAL_RANGES].tolist()
    terms = residual.used_terms(k[:_RESIDUAL_COEFS])   # only these: the sum is the same
    phi = residual.features(ranges, twist, rate, terms)
    change = residual.correction(k[:_RESIDUAL_COEFS].tolist(), phi, terms)
    gains = k[_RESIDUAL_GAINS:_RESIDUAL_GAINS + 3]
    change = np.stack([change[..., 0] * gains[0], change[..., 1] * gains[1],
                       change[..., 2] * gains[2]], axis=-1)
    return bounded_correction(twist, change)


def _residual_model_partials(k, twist, omega_l, omega_r, t_s, rate, wanted, inputs):
    ranges = k[_RESIDUAL_COEFS:_RESIDUAL_COEFS + _RESIDUAL_RANGES].tolist()
    coef = k[:_RESIDUAL_COEFS].reshape(len(residual.OUTPUTS), len(residual.TERMS))
    gains = k[_RESIDUAL_GAINS:_RESIDUAL_GAINS + 3]
    # the terms in use and those of the wanted coefficients (the others' values are not read)
    count = len(residual.TERMS)
    terms = sorted(set(residual.used_terms(k[:_RESIDUAL_COEFS]))
                   | {j % count for j in wanted if j < _RESIDUAL_COEFS})
    phi = residual.features(ranges, twist, rate, terms)  # (..., T)
    raw = np.einsum('ot,...t->...o', coef, phi)
    change = raw * gains
    d_change_twist = np.zeros(np.shape(twist) + (3,))
    d_change_rate = np.zeros(np.shape(twist) + (3,))
    if any(_RESIDUAL_COEFS <= j < _RESIDUAL_COEFS + _RESIDUAL_RANGES for j in wanted):
        _, d_phi_ranges = residual.feature_gradients(ranges, twist, rate)  # (..., T, 8)
    if inputs:
        d_inputs = (residual.correction_gradient(coef, ranges, twist, rate)
                    * gains[:, None])  # (..., 3, 4)
        d_change_twist[..., 0], d_change_twist[..., 2] = d_inputs[..., 0], d_inputs[..., 1]
        d_change_rate[..., 0], d_change_rate[..., 2] = d_inputs[..., 2], d_inputs[..., 3]
    count = len(residual.TERMS)
    d_change_k = np.zeros(np.shape(twist) + (len(wanted),))
    for c, j in enumerate(wanted):
        if j < _RESIDUAL_COEFS:
            d_change_k[..., j // count, c] = phi[..., j % count] * gains[j // count]
        elif j < _RESIDUAL_COEFS + _RESIDUAL_RANGES:
            d_change_k[..., c] = (np.einsum('ot,...t->...o', coef,
                                            d_phi_ranges[..., j - _RESIDUAL_COEFS])
                                  * gains)
        elif j >= _RESIDUAL_GAINS:
            d_change_k[..., j - _RESIDUAL_GAINS, c] = raw[..., j - _RESIDUAL_GAINS]
        # the level only says which coefficients are zero: no slope of its own
    return _bounded_partials(twist, change, d_change_twist, d_change_rate, d_change_k)


# the last residual model's values and their terms in use (one tuple: read and set atomically)
_RESIDUAL_PLAN: tuple = ((), None)


def _scalar_residual_model(k, vx, vy, w, omega_l, omega_r, t_s, rate):
    global _RESIDUAL_PLAN
    last = _RESIDUAL_PLAN
    if last[0] is not k:   # the node hands the same tuple at every sample of a bound model
        last = _RESIDUAL_PLAN = (k, residual.correction_plan(k[:_RESIDUAL_COEFS]))
    ranges = k[_RESIDUAL_COEFS:_RESIDUAL_COEFS + _RESIDUAL_RANGES]
    cx, cy, cw = residual.scalar_planned_correction(last[1], ranges, vx, w, rate[0], rate[2])
    cx = cx * k[_RESIDUAL_GAINS]
    cy = cy * k[_RESIDUAL_GAINS + 1]
    cw = cw * k[_RESIDUAL_GAINS + 2]
    v = abs(vx)
    a = abs(w)
    linear = v + a * SLIP_LEVER_M
    angular = a + v / SLIP_LEVER_M
    cx = min(max(cx, -linear), linear)
    cy = min(max(cy, -linear), linear)
    cw = min(max(cw, -angular), angular)
    return vx + cx, vy + cy, w + cw


def residual_jacobian(k: Sequence[float], twist: Sequence[float], rate: Sequence[float],
                      index: Sequence[int] | None = None) -> list[tuple[float, float, float]]:
    """Return d(twist)/d(coefficient) of the residual model at one sample, (d vx, d vy, d w).

    The correction is linear in its coefficients: output o's coefficient of term j moves
    component o by the term's value times the output's gain (the bound is left out).
    ``index``: only these coefficients (positions among the extension's), in that order.
    """
    ranges = tuple(k[_RESIDUAL_COEFS:_RESIDUAL_COEFS + _RESIDUAL_RANGES])
    if index is not None:
        count = len(residual.TERMS)
        phi = residual.scalar_terms(ranges, twist[0], twist[2], rate[0], rate[2],
                                    sorted({i % count for i in index}))
        rows = []
        for i in index:
            row = [0.0, 0.0, 0.0]
            row[i // count] = phi[i % count] * k[_RESIDUAL_GAINS + i // count]
            rows.append((row[0], row[1], row[2]))
        return rows
    phi = residual.scalar_features(ranges, twist[0], twist[2], rate[0], rate[2])
    zero = (0.0, 0.0, 0.0)
    out = []
    for o in range(len(residual.OUTPUTS)):
        gain = k[_RESIDUAL_GAINS + o]
        for value in phi:
            row = list(zero)
            row[o] = value * gain
            out.append((row[0], row[1], row[2]))
    return out


def _residual_specs() -> tuple[ParamSpec, ...]:
    specs = []
    units = {name: unit for name, unit, _ in residual.INPUTS}
    for out_name, out_unit in residual.OUTPUTS:
        for term, level, _, _ in residual.TERMS:
            specs.append(_spec(f'{out_name}_{term}', out_unit, 0.0, -10.0, 10.0,
                               f'{out_name} correction per unit of the scaled term {term} '
                               f'(level {level})'))
    for name, _, text in residual.INPUTS:
        for side, word in (('lo', 'lowest'), ('hi', 'highest')):
            specs.append(_spec(f'{name}_{side}', units[name], 0.0, -1e4, 1e4,
                               f'{word} {text} the model was fitted on (inputs are clamped to '
                               'the range, scaled by its largest magnitude)'))
    specs.append(_spec('level', '-', 0.0, 0.0, float(max(residual.LEVELS)),
                       'library level chosen on held-out likelihood (terms above it are 0)'))
    for out_name, _ in residual.OUTPUTS:
        specs.append(_spec(f'gain_{out_name}', '-', 1.0, 0.0, 3.0,
                           f'gain on the {out_name} correction, refined on whole segments (the '
                           'regression fits velocities, the segments poses)'))
    return tuple(specs)


_TWIST_FUNCTIONS = {
    'speed_slip': _speed_slip,
    'direction_asymmetry': _direction_asymmetry,
    'lateral_skid': _lateral_skid,
    'icr_offset': _icr_offset,
    'ratio_yaw_slip': _ratio_yaw_slip,
    'terrain_regime': _terrain_regime,
    'acceleration_slip': _acceleration_slip,
    'sparse_correction': _sparse_correction,
    'residual_model': _residual_model,
}

# The twist rules that read the rate (the others are given none: it is not computed for them).
_USES_RATE = frozenset({'acceleration_slip', 'sparse_correction', 'residual_model'})

_PARTIAL_FUNCTIONS = {
    'speed_slip': _speed_slip_partials,
    'direction_asymmetry': _direction_asymmetry_partials,
    'lateral_skid': _lateral_skid_partials,
    'icr_offset': _icr_offset_partials,
    'ratio_yaw_slip': _ratio_yaw_slip_partials,
    'terrain_regime': _terrain_regime_partials,
    'acceleration_slip': _acceleration_slip_partials,
    'sparse_correction': _sparse_correction_partials,
    'residual_model': _residual_model_partials,
}

_SCALAR_FUNCTIONS = {
    'speed_slip': _scalar_speed_slip,
    'direction_asymmetry': _scalar_direction_asymmetry,
    'lateral_skid': _scalar_lateral_skid,
    'icr_offset': _scalar_icr_offset,
    'ratio_yaw_slip': _scalar_ratio_yaw_slip,
    'terrain_regime': _scalar_terrain_regime,
    'acceleration_slip': _scalar_acceleration_slip,
    'residual_model': _scalar_residual_model,
}


def _start_offset(hints: FitHints) -> dict[str, float]:
    # The whole lag the trace found (the stamp convention included), inside the bounds.
    return {'offset_s': float(np.clip(hints.lag_s + hints.convention_s, -0.45, 0.45))}


def _start_lag(hints: FitHints) -> dict[str, float]:
    # A delay and a first-order lag shift a drive alike: the lag found is a fair time constant.
    return {'tau_s': float(np.clip(abs(hints.lag_s), 0.03, 1.5))}


def _start_slip(hints: FitHints) -> dict[str, float]:
    # A body that lags while speeding up looks like a lag: the lag found is a fair start.
    return {'tau_s': float(np.clip(abs(hints.lag_s), 0.03, 0.9))}


def _over_the_drive(hints: FitHints) -> tuple[float, float]:
    return 0.0, hints.duration_s


_ALL: tuple[Extension, ...] = (
    Extension(
        'time_offset', 'Time offset between wheel stamps and motion', 'timing',
        'pose(t + offset) = integral of the wheel-driven twist up to t', 'lag (cross-correlation)',
        (_spec('offset_s', 's', 0.0, -0.5, 0.5,
               'the true motion lags the wheel stamps by this (published stamps shift by it)'),),
        ('offset_s',), start=_start_offset, residual_view=('v_x', 'd_wheel_sum', False)),
    Extension(
        'first_order_lag', 'First-order response of the body', 'dynamics',
        'tau d(twist)/dt = twist_model - twist (exact for inputs held between samples)',
        'wheel acceleration',
        (_spec('tau_s', 's', 0.0, 0.0, 2.0, 'time constant of the body twist response'),),
        ('tau_s',), start=_start_lag, short_alias=('tau_s', 'time_offset'),
        residual_view=('v_x', 'd_wheel_sum', False), group='lag',
        lags=('tau_s', 'tau_s', 'tau_s')),
    Extension(
        'forward_lag', 'First-order response of the forward speed only', 'dynamics',
        'tau d(v_x)/dt = v_x,model - v_x (v_y and omega follow at once)', 'forward acceleration',
        (_spec('tau_s', 's', 0.0, 0.0, 2.0, 'time constant of the forward speed response'),),
        ('tau_s',), start=_start_lag, residual_view=('v_x', 'd_body_speed', False),
        group='lag', lags=('tau_s', None, None)),
    Extension(
        'yaw_lag', 'First-order response of the yaw rate only', 'dynamics',
        'tau d(omega)/dt = omega_model - omega (v_x and v_y follow at once)', 'yaw acceleration',
        (_spec('tau_s', 's', 0.0, 0.0, 2.0, 'time constant of the yaw rate response'),),
        ('tau_s',), start=_start_lag, residual_view=('omega', 'd_yaw_rate', False),
        group='lag', lags=(None, None, 'tau_s')),
    Extension(
        'component_lags', 'First-order responses of forward speed and yaw rate', 'dynamics',
        'tau_v d(v_x)/dt = v_x,model - v_x; tau_w d(omega)/dt = omega_model - omega',
        'forward and yaw acceleration',
        (_spec('tau_v_s', 's', 0.0, 0.0, 2.0, 'time constant of the forward speed response'),
         _spec('tau_w_s', 's', 0.0, 0.0, 2.0, 'time constant of the yaw rate response')),
        ('tau_v_s', 'tau_w_s'),
        start=lambda hints: {f'tau_{c}_s': _start_lag(hints)['tau_s'] for c in 'vw'},
        residual_view=('v_x', 'd_body_speed', False), group='lag',
        lags=('tau_v_s', None, 'tau_w_s')),
    Extension(
        'backlash', 'Drivetrain backlash: play after a wheel reverses', 'wheels',
        'each wheel follows its motor (the encoder) within a play: d = wheel - motor angle '
        'stays in [-play/2, play/2]; after a reversal the motor turns through the play before '
        'the wheel moves',
        'motion since a wheel reversed',
        (_spec('play_rad', 'rad', 0.0, 0.0, 3.0,
               'angle the motor turns after a reversal before its wheel moves'),),
        ('play_rad',), start=lambda hints: {'play_rad': 0.2},
        residual_view=('v_x', 'reversal_speed', False)),
    Extension(
        'speed_slip', 'Longitudinal slip growing with speed', 'twist',
        'v_x *= 1 - min(k |v_x|, 0.8)', 'v_x |v_x|',
        (_spec('k', 's/m', 0.0, 0.0, 2.0, 'slip fraction per m/s of forward speed'),),
        ('k',), residual_view=('v_x', 'v_abs_v', False)),
    Extension(
        'direction_asymmetry', 'More slip when reversing', 'twist',
        'v_x *= 1 - k clip(-v_x / blend, 0, 1)', 'direction of travel',
        (_spec('k', '-', 0.0, -0.9, 0.9, 'extra fraction of v_x lost when driving backward'),
         ParamSpec('blend_m_s', 'm/s', 0.05, 0.0, 1.0,
                   'speed over which forward blends into backward', lower_open=True)),
        ('k',), residual_view=('v_x', 'body_speed', False)),
    Extension(
        'lateral_skid', 'Lateral skid in turns (centrifugal)', 'twist',
        'v_y += k v_x omega', 'v_x omega',
        (_spec('k', 's', 0.0, -1.0, 1.0, 'lateral speed per unit of v_x omega'),),
        ('k',), residual_view=('v_y', 'v_omega', False)),
    Extension(
        'icr_offset', 'Rotation centre offset along the body', 'twist',
        'v_y += x omega', 'yaw rate',
        (_spec('x_m', 'm', 0.0, -2.0, 2.0,
               'the tracked point lies x ahead of the rotation centre (an ICR behind base_link, '
               'or a ground-truth frame mounted ahead of it)'),),
        ('x_m',), residual_view=('v_y', 'yaw_rate', False)),
    Extension(
        'ratio_yaw_slip', 'Yaw slip at a wheel-speed ratio', 'twist',
        'omega *= 1 - k exp(-((ratio - peak) / width)^2), ratio = slow/fast side (same sign)',
        'wheel-speed ratio',
        (_spec('k', '-', 0.0, -0.9, 0.95, 'largest fraction of the yaw rate lost'),
         ParamSpec('ratio_peak', '-', 0.5, 0.0, 1.0,
                   'speed ratio (slow / fast side) where the loss peaks'),
         ParamSpec('ratio_width', '-', 0.15, 0.0, 1.0, 'width of the loss around the peak',
                   lower_open=True)),
        ('k', 'ratio_peak'), residual_view=('omega', 'wheel_ratio', True)),
    Extension(
        'terrain_regime', 'Terrain regime switching in time', 'twist',
        '(v_x, omega) *= 1 - k once the time since the drive start >= switch_s',
        'time in drive',
        (_spec('k', '-', 0.0, -0.9, 0.9, 'fraction of v_x and omega lost in the regime'),
         _spec('switch_s', 's', 0.0, 0.0, 1e6, 'time since the drive start when it begins')),
        ('k',), scan=('switch_s',), refine=False, scan_range=_over_the_drive,
        residual_view=('v_x', 'time_in_drive', True)),
    Extension(
        'acceleration_slip', 'Forward slip while the wheels speed up', 'twist',
        'v_x -= sign(v_x) min(tau |dv/dt|, |v_x|) where v_x dv/dt > 0 (speeding up), dv/dt the '
        "base forward speed's backward difference over one wheel sample",
        'forward acceleration while speeding up',
        (_spec('tau_s', 's', 0.0, 0.0, 1.0,
               'forward speed lost per m/s^2 of wheel acceleration while speeding up'),),
        ('tau_s',), start=_start_slip, residual_view=('v_x', 'speeding_up', False)),
    Extension(
        'sparse_correction', 'Sparse regression on a library of twist terms', 'twist',
        'twist += C @ [v, w, v|v|, w|w|, v w, |v|, |w|, dv, dw, dv_up] (terms chosen by STLSQ; '
        'dv, dw: backward differences over at least 10 ms; dv_up: dv while speeding up), each '
        'change at most |v| + 2 m |w| (m/s) or |w| + |v| / 2 m (rad/s)',
        'selected library terms', _sparse_specs(), (), library=True,
        residual_view=('v_x', 'body_speed', False)),
    Extension(
        'residual_model', 'Data-driven residual of the body twist', 'twist',
        'twist += C phi(v, w, dv, dw): a library of smooth terms in levels (signals and '
        'magnitudes; products of a signal and a magnitude, smooth signs; rates, their '
        'speeding-up parts and v dv, v |dv|; the turn fraction times v and w; cubics; spline '
        'hinges on |v| and |w|) of the base twist and its rate, inputs clamped to the '
        'fitted range and scaled to [-1, 1]; C by Bayesian linear regression, the level on '
        'held-out likelihood, a gain per component on whole segments; each change at most '
        '|v| + 2 m |w| (m/s) or |w| + |v| / 2 m (rad/s)',
        'smooth function of the wheel-speed state', _residual_specs(),
        ('gain_vx', 'gain_vy', 'gain_wz'), regression=True,
        residual_view=('v_x', 'body_speed', False)),
)

EXTENSIONS: dict[str, Extension] = {ext.name: ext for ext in _ALL}
EXTENSION_NAMES: tuple[str, ...] = tuple(EXTENSIONS)
# Order in which extensions are applied: timing, wheels, twist stage (registry order), dynamics.
_STAGE_ORDER = {'timing': 0, 'wheels': 1, 'twist': 2, 'dynamics': 3}


def get_extension(name: str) -> Extension:
    """Look an extension up by name; an unknown name lists the known ones."""
    try:
        return EXTENSIONS[name]
    except KeyError:
        raise ParameterError(f'unknown extension {name!r}; known extensions are: '
                             f'{", ".join(EXTENSION_NAMES)}') from None


def ordered(names: Sequence[str], exclusive: bool = True) -> tuple[str, ...]:
    """Return extension names in application order, checking each is known and unique.

    ``exclusive``: also check that no two share a group (a model's structure; a list of
    candidates may hold rivals).
    """
    seen = []
    for name in names:
        group = get_extension(name).group
        if name in seen:
            raise ParameterError(f'extension {name!r} is listed twice')
        rival = [other for other in seen
                 if exclusive and group and EXTENSIONS[other].group == group]
        if rival:
            members = ', '.join(n for n, e in EXTENSIONS.items() if e.group == group)
            raise ParameterError(f'extensions {rival[0]!r} and {name!r} cannot be combined (both '
                                 f'are a {group}); keep one of: {members}')
        seen.append(name)
    return tuple(sorted(seen, key=lambda n: (_STAGE_ORDER[EXTENSIONS[n].stage],
                                             EXTENSION_NAMES.index(n))))
