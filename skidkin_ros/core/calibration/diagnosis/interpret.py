"""What a fitted residual model depends on: which signals, how much, and the slice to plot.

The residual model's correction of each twist component is a sum of library terms, each a
function of some inputs (:data:`skidkin_ros.core.kinematics.residual.TERM_INPUTS`: the forward
speed v, the yaw rate w, their interaction v*w, the rates dv, dw). Over the training poses, the
terms of one input group add up to that group's part of the correction; its share is the part's
variance over the sum of the parts' variances. The group with the largest share is the signal
that explains most, and the report plots the learned correction against it (a slice through the
learned function, with the residual it was fitted to).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from skidkin_ros.core.kinematics import residual

__all__ = ['Dependence', 'residual_dependence', 'residual_correction_at']

_COMPONENTS = {'vx': 'v_x', 'vy': 'v_y', 'wz': 'omega'}


@dataclass(frozen=True)
class Dependence:
    """One corrected component: its RMS correction and each input group's share, largest first."""

    component: str
    rms: float
    shares: tuple[tuple[str, float], ...]

    @property
    def signal(self) -> str:
        """Return the trace signal of the input group that explains most."""
        return residual.INPUT_SIGNALS[self.shares[0][0]]

    def text(self) -> str:
        unit = 'rad/s' if self.component == 'omega' else 'm/s'
        parts = ', '.join(f'{group} {share:.0%}' for group, share in self.shares if share >= 0.05)
        return (f'{self.component} correction RMS {self.rms:.3g} {unit}, follows {parts} '
                f'(plotted against {self.signal})')


def _inputs(signals: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(signals['body_speed'], dtype=float)
    zero = np.zeros_like(v)
    twist = np.stack([v, zero, np.asarray(signals['yaw_rate'], dtype=float)], axis=-1)
    rate = np.stack([np.asarray(signals.get('d_body_speed', zero), dtype=float), zero,
                     np.asarray(signals.get('d_yaw_rate', zero), dtype=float)], axis=-1)
    return twist, rate


def residual_correction_at(values: Mapping[str, float], signals: Mapping[str, np.ndarray]
                           ) -> np.ndarray:
    """Return the learned correction (N, 3) at the poses (the base twist and rate as inputs)."""
    twist, rate = _inputs(signals)
    ranges = [values.get(name, 0.0) for name in residual.range_names()]
    phi = residual.features(ranges, twist, rate)
    coef = [values.get(name, 0.0) * values.get(f'gain_{name.split("_")[0]}', 1.0)
            for name in residual.coefficient_names()]
    return residual.correction(coef, phi)


def residual_dependence(values: Mapping[str, float], signals: Mapping[str, np.ndarray],
                        valid: np.ndarray | None = None) -> tuple[Dependence, ...]:
    """Return the dependence of every corrected component, the largest correction first."""
    twist, rate = _inputs(signals)
    if valid is not None:
        twist, rate = twist[valid], rate[valid]
    ranges = [values.get(name, 0.0) for name in residual.range_names()]
    phi = residual.features(ranges, twist, rate)
    names = residual.term_names()
    out = []
    for out_name, _ in residual.OUTPUTS:
        coef = np.array([values.get(f'{out_name}_{term}', 0.0) for term in names])
        coef = coef * values.get(f'gain_{out_name}', 1.0)
        if not np.any(coef) or phi.shape[0] == 0:
            continue
        parts: dict[str, np.ndarray] = {}
        for j, term in enumerate(names):
            if coef[j] != 0.0:
                group = residual.TERM_INPUTS[term]
                parts[group] = parts.get(group, 0.0) + coef[j] * phi[:, j]
        total = phi @ coef
        spread = {group: float(np.var(part)) for group, part in parts.items()}
        whole = sum(spread.values())
        if not whole > 0.0:
            continue
        shares = tuple(sorted(((g, s / whole) for g, s in spread.items()), key=lambda i: -i[1]))
        out.append(Dependence(_COMPONENTS[out_name], float(np.sqrt(np.mean(total ** 2))),
                              shares))
    return tuple(sorted(out, key=lambda d: -d.rms * (1.0 if d.component != 'omega' else 0.3)))
