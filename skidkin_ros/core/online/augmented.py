"""Online calibration of an augmented model: the base model's parameters and its extensions'.

The offline calibrator fits an augmented model through a
:class:`~skidkin_ros.core.calibration.engine.ParameterLayout`: every base parameter, then the
parameters each extension declares as fitted (``Extension.fitted``; a blend width or a ratio
width keeps its value). Online, the same layout is wrapped as a kinematic model
(:class:`LayoutModel`) whose twist is the bound augmented model's
(:meth:`BoundAugmented.twist`), so the calibrator's own functions score it:
:func:`~skidkin_ros.core.calibration.fitting.segment_errors` rolls a segment out through the
augmented twist, the Jacobian is the central difference of
:func:`~skidkin_ros.core.calibration.fitting.predict_end_poses` (the step
:func:`~skidkin_ros.core.calibration.noise_fit.parameter_sensitivity` takes), the noise weighting
is the base model's noise (an augmented model publishes its base model's noise), and the window,
the eigen-direction rule, the change detection and the reference gates are the plain model's
(:class:`~skidkin_ros.core.online.calibrator.OnlineCalibrator`, unchanged; the two places
that ask for the Jacobian by model name, the window's residuals and a ground's score with its
parameter uncertainty, are overridden here to take it from the layout model).

Which extensions can be learned online (``ONLINE_EXTENSIONS``): those of the twist stage whose
formula depends on the wheel speeds and the base twist only (speed_slip, direction_asymmetry,
lateral_skid, icr_offset, ratio_yaw_slip). The others need what a learning segment does not
carry: the time since the drive started (terrain_regime), the base twist's rate over each wheel
sample (acceleration_slip, and the residual_model's and the sparse_correction's rate terms: a
segment's wheel steps are merged into 50 ms blocks), or a state carried across the segment's
start (the lags, time_offset). A configuration with one of them is refused with that reason.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Mapping

import numpy as np

from skidkin_ros.core.calibration.engine import BASE, ParameterLayout
from skidkin_ros.core.calibration.fitting import predict_end_poses, segment_errors
from skidkin_ros.core.calibration.noise_fit import (mahalanobis, segment_covariances,
                                                    segment_motion, SegmentMotion)
from skidkin_ros.core.calibration.segments import segment_frame_error, SegmentSet
from skidkin_ros.core.kinematics.augmented import BoundAugmented
from skidkin_ros.core.kinematics.extensions import get_extension
from skidkin_ros.core.kinematics.models import BoundModel, get_model, KinematicModel
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.reference import ONLINE_EXTENSIONS
from skidkin_ros.core.odometry.uncertainty import ParameterUncertainty
from skidkin_ros.core.online.calibrator import OnlineCalibrator
from skidkin_ros.core.online.grounds import Ground
from skidkin_ros.core.online.window import _stack

__all__ = ['LayoutModel', 'LayoutUncertainty', 'AugmentedCalibrator', 'ONLINE_EXTENSIONS']

# Relative step of the central differences (parameter_sensitivity's).
REL_STEP = 1e-6


class LayoutModel(KinematicModel):
    """An augmented model's fitted parameters as one kinematic model (module docstring).

    Parameter names: the base model's, then ``<extension>.<parameter>`` for each fitted
    extension parameter, in the layout's order.
    """

    predicts_lateral = True
    name = 'augmented'

    def __init__(self, layout: ParameterLayout) -> None:
        self.layout = layout
        self.base = get_model(layout.base_name)
        specs = []
        for i, j in layout.free:
            if i == BASE:
                specs.append(self.base.params[j])
            else:
                ext = get_extension(layout.extensions[i])
                specs.append(replace(ext.params[j], name=f'{ext.name}.{ext.params[j].name}'))
        self.params = tuple(specs)
        self.title = f'{layout.base_name} + {", ".join(layout.extensions)}'

    def defaults(self, geometry: Geometry) -> dict[str, float]:
        return self.mapping(self.layout.vector())

    def check_constraints(self, k: np.ndarray) -> None:
        base_k, _ = self.layout.parameters(np.asarray(k, dtype=float))
        self.base.check_constraints(base_k)

    def source(self, k: np.ndarray) -> BoundAugmented:
        """Return the bound augmented model with the fitted entries set from ``k``."""
        base_k, ext_k = self.layout.parameters(np.asarray(k, dtype=float))
        return BoundAugmented(BoundModel(self.base, self.layout.geometry, base_k),
                              self.layout.extensions, ext_k)

    def twist(self, k: np.ndarray, geometry: Geometry, omega_l, omega_r) -> np.ndarray:
        return np.asarray(self.source(k).twist(omega_l, omega_r), dtype=float)

    def file_values(self, k: np.ndarray) -> dict[str, float]:
        """Return the flat parameters-file entries of ``k`` (models.<base>.*, augmented.*)."""
        base_values, ext_values = self.layout.values(np.asarray(k, dtype=float))
        out = {f'models.{self.base.name}.{name}': value for name, value in base_values.items()}
        for ext, values in ext_values.items():
            out.update({f'augmented.{ext}.{name}': value for name, value in values.items()})
        return out


def online_layout(base_name: str, geometry: Geometry, base_values: Mapping[str, float],
                  ext_values: Mapping[str, Mapping[str, float]],
                  extensions: tuple[str, ...]) -> ParameterLayout:
    """Return the layout learned online: every base parameter, each extension's fitted ones."""
    return ParameterLayout.build(base_name, geometry, base_values, ext_values, extensions, True,
                                 {name: get_extension(name).fitted for name in extensions})


class AugmentedCalibrator(OnlineCalibrator):
    """:class:`OnlineCalibrator` for a :class:`LayoutModel` (module docstring)."""

    model: LayoutModel

    def _residuals(self, ground: Ground, segments: list[SegmentSet]
                   ) -> tuple[np.ndarray, np.ndarray]:
        batch = _stack(segments)
        k = ground.k
        errors = segment_errors(self.model, k, self.geometry, batch)
        sens = np.zeros((len(batch), 3, k.size))
        for j in range(k.size):
            step = REL_STEP * max(abs(float(k[j])), 1.0)
            plus, minus = k.copy(), k.copy()
            plus[j] += step
            minus[j] -= step
            sens[:, :, j] = segment_frame_error(
                batch.start, predict_end_poses(self.model, plus, self.geometry, batch),
                predict_end_poses(self.model, minus, self.geometry, batch)) / (2.0 * step)
        return errors, sens * self.scale

    def _score(self, ground: Ground, seg: SegmentSet, motion_cov: np.ndarray,
               with_parameters: bool) -> tuple[np.ndarray, np.ndarray | None, float]:
        if not with_parameters:  # segment_errors takes the layout model as it is
            return super()._score(ground, seg, motion_cov, with_parameters)
        errors, sens = self._residuals(ground, [seg])
        cov = (motion_cov + self._reference_cov()
               + sens[0] @ np.linalg.inv(ground.info) @ sens[0].T)
        return errors[0], sens[0], float(mahalanobis(cov[None], errors[0][None])[0])

    def _motion_cov(self, seg: SegmentSet) -> np.ndarray:
        base_k, _ = self.model.layout.parameters(self.active.k)
        motion = segment_motion(self.model.base.name, self.model.base.mapping(base_k),
                                self.geometry, seg)
        return segment_covariances(self.noise, motion)[0]

    def _noise_motion(self, k: np.ndarray, seg: SegmentSet) -> SegmentMotion:
        # The noise bases are the base model's steps (as in _motion_cov); the parameter
        # covariance is left out of the fixed term, so the learned factor errs high (covers
        # the parameters' share too): conservative, never over-confident.
        base_k, _ = self.model.layout.parameters(k)
        return segment_motion(self.model.base.name, self.model.base.mapping(base_k),
                              self.geometry, seg)

    def bound_model(self) -> BoundAugmented:
        return self.model.source(self.in_force()[0].copy())

    def uncertainty(self) -> ParameterUncertainty | None:
        k, covariance = self.in_force()   # the active ground's, or the blend while holding
        return LayoutUncertainty.of_layout(self.model, k, self.geometry, covariance)


@dataclass(frozen=True)
class LayoutUncertainty(ParameterUncertainty):
    """The parameter uncertainty of a layout model, carried per wheel sample on floats.

    d(twist)/dk_j is the central difference of the augmented twist at the step's wheel speeds
    (as :class:`ParameterUncertainty` takes it for a model not linear in them), with the 2p
    perturbed models bound once per parameter vector and evaluated on plain floats
    (:meth:`BoundAugmented.scalar_memoryless`) instead of a model rebuilt per sample and
    parameter: at 1 kHz the rebuilt form cost 150 us per sample.
    """

    pairs: tuple = ()   # per parameter: (model at k + h, model at k - h, 1 / 2h)

    @classmethod
    def of_layout(cls, model: LayoutModel, k: np.ndarray, geometry: Geometry,
                  covariance: np.ndarray) -> 'LayoutUncertainty | None':
        k = np.asarray(k, dtype=float)
        covariance = np.asarray(covariance, dtype=float)
        if k.size == 0 or not np.any(covariance):
            return None
        pairs = []
        for j in range(k.size):
            step = REL_STEP * max(abs(float(k[j])), 1.0)
            plus, minus = k.copy(), k.copy()
            plus[j] += step
            minus[j] -= step
            pairs.append((model.source(plus), model.source(minus), 1.0 / (2.0 * step)))
        return cls(covariance, (), (model, tuple(k.tolist()), geometry, REL_STEP), tuple(pairs))

    def twist_jacobian(self, vx: float, vy: float, w: float,
                       wheels: tuple[float, float] | None = None
                       ) -> list[tuple[float, float, float]] | None:
        if wheels is None:
            return None
        left, right = wheels
        out = []
        for plus, minus, inverse in self.pairs:
            a = plus.scalar_memoryless(left, right, 0.0)
            b = minus.scalar_memoryless(left, right, 0.0)
            out.append(((a[0] - b[0]) * inverse, (a[1] - b[1]) * inverse,
                        (a[2] - b[2]) * inverse))
        return out
