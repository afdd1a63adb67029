"""kiss-icp settings of the lidar ground truth (IcpConfig) and the automatic voxel size.

One job: everything a registration depends on, checked when set, and kiss-icp's config built
from it (see :mod:`skidkin_ros.adapters.lidar_gt`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from skidkin_ros.errors import ParameterError

__all__ = ['auto_voxel_size', 'IcpConfig', 'VOXEL_PER_SPACING']


@dataclass(frozen=True)
class IcpConfig:
    """kiss-icp settings and the checks of its input: everything a registration depends on.

    Ranges and voxel size in m (voxel_size_m None: from the data, :func:`auto_voxel_size`;
    kiss-icp's own rule, max_range / 100, ties it to the sensor instead of the scene);
    ``max_points_per_voxel``, ``max_iterations`` and ``convergence`` are kiss-icp's mapping and
    registration settings; ``stride``: register one scan in ``stride`` (the others get status
    'stride'); ``max_threads``: kiss-icp's threads per registration (1: the result does not
    depend on the machine or on how many run at once; kiss-icp 1.3's threaded reduction changes
    the last bits of the poses, docs/ground-truth.md; 0: every core). ``quality_points``:
    source points sampled per frame to measure the registration's quality.
    The defaults come from the speed/accuracy table of lab/bench/icp_settings.py
    (docs/benchmarks.md).
    """

    max_range_m: float = 100.0
    min_range_m: float = 0.5
    voxel_size_m: float | None = None
    max_points_per_voxel: int = 20
    max_iterations: int = 500
    convergence: float = 1e-3
    stride: int = 1
    deskew: bool = True
    max_threads: int = 1
    min_points: int = 200
    min_time_spread_s: float = 1e-4
    max_time_spread_s: float = 1.0
    quality_points: int = 400

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_range_m < self.max_range_m:
            raise ParameterError('IcpConfig: need 0 <= min_range_m < max_range_m (m), got '
                                 f'{self.min_range_m}, {self.max_range_m}')
        if self.voxel_size_m is not None and not self.voxel_size_m > 0.0:
            raise ParameterError(f'IcpConfig.voxel_size_m must be > 0 m, got '
                                 f'{self.voxel_size_m}')
        for name in ('min_time_spread_s', 'max_time_spread_s', 'convergence'):
            if not getattr(self, name) > 0.0:
                raise ParameterError(f'IcpConfig.{name} must be > 0, got {getattr(self, name)}')
        for name, low in (('min_points', 1), ('max_points_per_voxel', 1),
                          ('max_iterations', 1), ('stride', 1), ('max_threads', 0),
                          ('quality_points', 0)):
            value = getattr(self, name)
            if not isinstance(value, int) or value < low:
                raise ParameterError(f'IcpConfig.{name} must be a whole number >= {low}, got '
                                     f'{value!r}')

    @property
    def voxel_size(self) -> float:
        if self.voxel_size_m is None:
            raise ParameterError('IcpConfig.voxel_size_m is not resolved yet: use '
                                 'with_voxel_for(first cloud) first')
        return self.voxel_size_m

    def with_voxel_for(self, xyz: np.ndarray) -> 'IcpConfig':
        """Return this config with its voxel size set from a cloud when it is automatic."""
        if self.voxel_size_m is not None:
            return self
        return replace(self, voxel_size_m=auto_voxel_size(xyz, self))

    def kiss_config(self) -> Any:
        """Return kiss-icp's KISSConfig built from ``load_config(None)`` with our settings."""
        from kiss_icp.config import load_config

        config = load_config(None)
        config.data.max_range = float(self.max_range_m)
        config.data.min_range = float(self.min_range_m)
        config.data.deskew = self.deskew
        config.mapping.voxel_size = float(self.voxel_size)
        config.mapping.max_points_per_voxel = int(self.max_points_per_voxel)
        config.registration.max_num_iterations = int(self.max_iterations)
        config.registration.convergence_criterion = float(self.convergence)
        config.registration.max_num_threads = int(self.max_threads)
        return config

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


# The automatic voxel: this many times the median spacing of neighbouring points of a scan.
VOXEL_PER_SPACING = 6.0
_VOXEL_RANGE_M = (0.2, 3.0)


def auto_voxel_size(xyz: np.ndarray, config: IcpConfig) -> float:
    """Return a voxel size (m) for kiss-icp from one cloud: 6 x its median point spacing.

    kiss-icp ties the voxel to the sensor's range (max_range / 100); what registers well is a
    voxel that holds a few points of the scan at hand, so it grows with how sparse the scan is:
    0.55 m for a 16-ring lidar at 0.5 deg in a courtyard (median spacing 9 cm), 1.4 m for the
    same lidar at 1 deg among trees (23 cm). The factor comes from the speed/accuracy table of
    lab/bench/icp_settings.py. Rounded to 5 cm, within 0.2-3 m.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(xyz, dtype=float).reshape(-1, 3)
    points = points[np.all(np.isfinite(points), axis=1)]
    with np.errstate(over='ignore'):  # beyond 1e154 m: an infinite range
        ranges = np.linalg.norm(points, axis=1)
    points = points[(ranges > config.min_range_m) & (ranges < config.max_range_m)]
    if points.shape[0] < 10:
        return 1.0
    spacing, _ = cKDTree(points).query(points, k=2)
    voxel = VOXEL_PER_SPACING * float(np.median(spacing[:, 1]))
    return float(np.clip(round(voxel / 0.05) * 0.05, *_VOXEL_RANGE_M))
