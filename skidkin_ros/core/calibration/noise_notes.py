"""What the held-out check of a calibrated noise model says in words (step 4's warnings).

:func:`noise_warnings` (what the check cannot support, per horizon) and :func:`band_notes` (why
the written model's covariance is outside its NEES band where it is).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from skidkin_ros.core.calibration.noise_fit import NoiseFit

__all__ = ['band_notes', 'noise_warnings']


def band_notes(fit: NoiseFit, path_m: Mapping[float, np.ndarray]) -> list[str]:
    """Say why the written model's covariance is outside its NEES band where it is.

    ``path_m``: the held-out segments' path lengths by horizon. Two reasons are stated when the
    numbers show them: a coverage scale > 1 (errors heavier-tailed than a Gaussian: at the
    maximum-likelihood scale fewer than 95 % fit inside, so the covariance that holds 95 %
    is conservative on average); and horizons whose segments are mostly whole windows shorter
    than the horizon (a windowed recording), where the check repeats the shorter ones.
    """
    out = []
    checks = [c for c in fit.consistency.horizons if c.verdict in ('conservative',
                                                                   'over-confident')]
    conservative = [c for c in checks if c.verdict == 'conservative']
    if conservative and fit.coverage_scale > 1.0:
        where = ', '.join(f'{c.horizon_m:g}' for c in conservative)
        nees = ', '.join(f'{c.mean_nees:.2f}' for c in conservative)
        out.append(f'{fit.model}: the covariance is conservative at {where} m (average NEES '
                   f'{nees}; band about [{conservative[0].band[0]:.2f}, '
                   f'{conservative[0].band[1]:.2f}]) and cannot be inside the band while it '
                   f'holds 95 % of the held-out errors: it is scaled by '
                   f'{fit.coverage_scale:.2f} to hold them, because these errors are '
                   'heavier-tailed than a Gaussian (at the maximum-likelihood scale fewer than '
                   '95 % fit inside); the 95 % coverage is kept')
    short = {}
    for check in checks:
        paths = path_m.get(check.horizon_m)
        if paths is not None and paths.size:
            share = float(np.mean(paths < 0.9 * check.horizon_m))
            if share > 0.5:
                short[check.horizon_m] = share
    if short:
        out.append(f'{fit.model}: ' + ' / '.join(f'{v * 100:.0f} %' for v in short.values())
                   + ' of the held-out ' + ' / '.join(f'{h:g}' for h in short)
                   + ' m segments are whole drives or windows shorter than their horizon (a '
                   'windowed recording): the checks there test the covariance on those '
                   'shorter stretches, not at these lengths')
    return out


def noise_warnings(fit: NoiseFit) -> list[str]:
    """Return what the held-out check of a noise model cannot support (one line per horizon).

    Over-confident horizons and horizons with too few segments are said; a conservative one is
    not (the coverage scale makes the covariance conservative for typical errors on purpose,
    and the per-horizon NEES is in the provenance).
    """
    out = []
    for check in fit.consistency.horizons:
        verdict = check.verdict
        if verdict in ('consistent', 'conservative'):
            continue
        if verdict == 'too few segments to tell':
            out.append(f'{fit.model}: only {check.segments} held-out segments of '
                       f'{check.horizon_m:g} m: too few to check the covariance there (the '
                       'data cannot support a consistency claim at this horizon); drive more')
        else:
            out.append(f'{fit.model}: the covariance is {verdict} on held-out '
                       f'{check.horizon_m:g} m segments (average NEES {check.mean_nees:.2f}, band '
                       f'[{check.band[0]:.2f}, {check.band[1]:.2f}], {check.segments} segments)')
    return out
