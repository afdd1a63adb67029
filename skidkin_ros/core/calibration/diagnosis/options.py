"""The options of a diagnosis: one frozen dataclass, validated, saved with the results."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from skidkin_ros.core.calibration.engine import check_sigma_diag, whitening
from skidkin_ros.core.calibration.segments import HorizonOptions
from skidkin_ros.core.kinematics.extensions import EXTENSION_NAMES, get_extension, ordered
from skidkin_ros.errors import ParameterError

__all__ = ['DiagnosisOptions']


@dataclass(frozen=True)
class DiagnosisOptions(HorizonOptions):
    """Everything that shapes a diagnosis (saved with the results as provenance)."""

    # The sparse fallback (a library extension) stays available by name; the residual model (a
    # regression extension) supersedes it by default.
    candidates: tuple[str, ...] = tuple(n for n in EXTENSION_NAMES
                                        if not get_extension(n).library)
    refit_base: bool = True
    folds: int = 3
    min_relative_gain: float = 0.05
    significance: float = 0.01
    max_extensions: int = 3
    max_nfev: int = 30
    smoothing_s: float = 0.35
    lag_range_s: float = 0.4
    sparse_thresholds: tuple[float, ...] = (0.1, 0.2, 0.4)
    scan_points: int = 12
    holdout_every: int = 3
    holdout_mode: str = 'auto'
    holdout_block_s: float = 60.0
    holdout_key: str | None = None
    max_dt_s: float = 0.5
    # Used under interval 'starting' only (the zero-order hold from the stamp): the other
    # conventions already place the speeds on their interval and need no stamp-convention row.
    stamp_convention: str = 'mid'
    trim: bool = False
    # Question the base model first (asymmetry, ICR offsets, ROC: :mod:`.base`).
    question_base: bool = True

    def __post_init__(self) -> None:
        ordered(self.candidates, exclusive=False)
        if self.stamp_convention not in ('mid', 'start'):
            raise ParameterError("stamp_convention must be 'mid' (wheel speeds describe the "
                                 "middle of the interval they are held over) or 'start', got "
                                 f'{self.stamp_convention!r}')
        if self.folds < 2:
            raise ParameterError(f'folds must be >= 2, got {self.folds!r}')
        if not 0.0 <= self.min_relative_gain < 1.0:
            raise ParameterError('min_relative_gain must be in [0, 1) (fraction of held-out '
                                 f'loss), got {self.min_relative_gain!r}')
        if not 0.0 < self.significance < 1.0:
            raise ParameterError(f'significance must be in (0, 1), got {self.significance!r}')
        check_sigma_diag(self.sigma_diag)
        if (not self.sparse_thresholds
                or not all(isinstance(t, (int, float)) and t > 0 for t in self.sparse_thresholds)):
            raise ParameterError('sparse_thresholds must be one or more coefficient thresholds '
                                 f'> 0, got {self.sparse_thresholds!r}')
        if not self.smoothing_s > 0:
            raise ParameterError(f'smoothing_s must be > 0 s, got {self.smoothing_s!r}')

    @property
    def whitening(self) -> np.ndarray:
        return whitening(self.sigma_diag)

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out['candidates'] = list(self.candidates)
        out['sigma_diag'] = list(self.sigma_diag)
        return out
