"""Parameter specifications: one spec per parameter feeds everything else.

The optimizer bounds, the ROS parameter descriptors, the parameters YAML and the docs tables
are all generated from these specs, so a name, unit or bound is written exactly once.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Callable, Mapping, Union

from skidkin_ros.errors import ParameterError

__all__ = ['Geometry', 'ParamSpec', 'GEOMETRY_SPECS', 'DEFAULT_GEOMETRY', 'check_value']

INF = math.inf
# The default robot, the one home of its numbers: a Clearpath Husky A200 (published geometry).
DEFAULT_WHEEL_RADIUS_M = 0.1651
DEFAULT_TRACK_WIDTH_M = 0.555


@dataclass(frozen=True)
class Geometry:
    """Measured robot geometry: wheel radius r and track width b (wheel separation)."""

    wheel_radius: float
    track_width: float

    def __post_init__(self) -> None:
        for spec in GEOMETRY_SPECS:
            check_value(spec, getattr(self, spec.name))

    def as_dict(self) -> dict[str, float]:
        return {'wheel_radius': float(self.wheel_radius), 'track_width': float(self.track_width)}


DefaultFn = Callable[[Geometry], float]


@dataclass(frozen=True)
class ParamSpec:
    """One model parameter: name, unit, default, bounds and a one-line description.

    ``default`` is a number or a function of the geometry; every model defaults to the ideal
    differential drive of the configured geometry (``default_doc`` says how, for the docs).
    Bounds are closed unless ``lower_open``/``upper_open`` say otherwise. ``fit_lower`` and
    ``fit_upper``, when set, narrow the range the calibrator searches (a fitted value on them is
    on a bound) while any value in the range still loads: a model constraint of the fit (roc's
    positive ICR gain) that must not make older parameters files unreadable.
    ``fit_lower_is_constraint``: ``fit_lower`` is part of the model, not a guard, so a fitted
    value on it is a valid constrained minimum (roc's beta_2 = 0: the gain does not decay, and
    roc is then edd_symmetric), not a sign that the data want another model.
    """

    name: str
    unit: str
    default: Union[float, DefaultFn]
    lower: float
    upper: float
    description: str
    default_doc: str = ''
    lower_open: bool = False
    upper_open: bool = False
    fit_lower: float | None = None
    fit_upper: float | None = None
    fit_lower_is_constraint: bool = False

    def default_for(self, geometry: Geometry) -> float:
        if callable(self.default):
            return float(self.default(geometry))
        return float(self.default)

    def range_text(self) -> str:
        lo = '-inf' if self.lower == -INF else f'{self.lower:g}'
        hi = 'inf' if self.upper == INF else f'{self.upper:g}'
        left = '(' if self.lower_open or self.lower == -INF else '['
        right = ')' if self.upper_open or self.upper == INF else ']'
        return f'{left}{lo}, {hi}{right}'

    def fit_range_text(self) -> str:
        """Return the range the calibrator searches (the range, narrowed by fit_lower/upper)."""
        lo, hi = self.optimizer_bounds(margin=0.0)
        if (lo, hi) == (self.lower, self.upper):
            return self.range_text()
        low = '(-inf' if lo == -INF else f'[{lo:g}'
        high = 'inf)' if hi == INF else f'{hi:g}]'
        return f'{low}, {high}'

    def optimizer_bounds(self, margin: float = 1e-6) -> tuple[float, float]:
        """Bounds for scipy's least_squares; open bounds are pulled in by a small margin."""
        lo = self.lower + margin if self.lower_open and self.lower != -INF else self.lower
        hi = self.upper - margin if self.upper_open and self.upper != INF else self.upper
        if self.fit_lower is not None:
            lo = max(lo, self.fit_lower)
        if self.fit_upper is not None:
            hi = min(hi, self.fit_upper)
        return lo, hi

    def contains(self, value: float) -> bool:
        if not math.isfinite(value):
            return False
        if value < self.lower or (self.lower_open and value == self.lower):
            return False
        if value > self.upper or (self.upper_open and value == self.upper):
            return False
        return True

    def on_bound(self, value: float, rel_tol: float = 1e-4) -> bool:
        """Tell whether a fitted value sits on a finite bound (the fit wanted to go further).

        A value on a ``fit_lower`` that is a model constraint (``fit_lower_is_constraint``)
        is not on a bound: see :meth:`at_constraint`.
        """
        if self.at_constraint(value, rel_tol):
            return False
        for bound in (self.lower, self.upper, self.fit_lower, self.fit_upper):
            if bound is None or not math.isfinite(bound):
                continue
            if abs(value - bound) <= rel_tol * max(1.0, abs(bound)):
                return True
        return False

    def at_constraint(self, value: float, rel_tol: float = 1e-4) -> bool:
        """Tell whether a fitted value sits on a lower bound that is part of the model."""
        bound = self.fit_lower
        return (self.fit_lower_is_constraint and bound is not None and math.isfinite(bound)
                and abs(value - bound) <= rel_tol * max(1.0, abs(bound)))


def check_value(spec: ParamSpec, value: object, prefix: str = '') -> float:
    """Return ``value`` as float or raise ParameterError naming the parameter and its range."""
    name = prefix + spec.name
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParameterError(
            f'parameter {name!r} must be a number in {spec.range_text()} {spec.unit}, '
            f'got {value!r} ({type(value).__name__})')
    number = float(value)
    if not spec.contains(number):
        raise ParameterError(
            f'parameter {name!r} = {number!r} is outside its allowed range '
            f'{spec.range_text()} {spec.unit} ({spec.description})')
    return number


GEOMETRY_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec('wheel_radius', 'm', DEFAULT_WHEEL_RADIUS_M, 0.0, 5.0, 'wheel radius r (measured)',
              default_doc=f'{DEFAULT_WHEEL_RADIUS_M:g} (Husky A200)', lower_open=True),
    ParamSpec('track_width', 'm', DEFAULT_TRACK_WIDTH_M, 0.0, 20.0,
              'track width b: distance between left and right wheel centres (measured)',
              default_doc=f'{DEFAULT_TRACK_WIDTH_M:g} (Husky A200)', lower_open=True),
)
DEFAULT_GEOMETRY = Geometry(DEFAULT_WHEEL_RADIUS_M, DEFAULT_TRACK_WIDTH_M)


def spec_table(specs: Mapping[str, ParamSpec]) -> list[tuple[str, str, str, str, str]]:
    """Rows (name, unit, default, range, description) for documentation tables."""
    rows = []
    for spec in specs.values():
        default = spec.default_doc or f'{spec.default_for(DEFAULT_GEOMETRY):g}'
        rows.append((spec.name, spec.unit, default, spec.range_text(), spec.description))
    return rows
