"""Online calibration of an augmented model: the base model's parameters and its extensions'.

The offline calibrator fits an augmented model through a
:class:`~skidkin_ros.core.calibration.engine.ParameterLayout`: every base parameter, then the
parameters each extension declares as fitted (``Extension.fitted``; a blend width or a ratio
width keeps its value). Online, the same layout is wrapped as a kinematic model
(:class:`LayoutModel`) whose twist is the bound augmented model's
(:meth:`BoundAugmented.twist`), so the calibrator's own functions score it:
:func:`~skidkin_ros.core.calibration.fitting.segment_errors` rolls a segment out through the
augmented twist and :func:`~skidkin_ros.core.calibration.fitting.segment_errors_jacobian` gives
its exact derivatives, from the layout model's exact twist gradient
(:meth:`LayoutModel.twist_gradient`: the diagnosis's forward-mode tangents,
:func:`~skidkin_ros.core.kinematics.augmented_tangents.interval_tangents`, built on each
extension's :meth:`~skidkin_ros.core.kinematics.extensions.Extension.partials`; one home for
the derivative of an augmented twist, offline and online), the noise weighting
is the base model's noise (an augmented model publishes its base model's noise), and the window,
the eigen-direction rule, the change detection and the reference gates are the plain model's
(:class:`~skidkin_ros.core.online.calibrator.OnlineCalibrator`, unchanged; the two places
that ask for the Jacobian by model name, the window's residuals and a ground's score with its
parameter uncertainty, are overridden here to take it from the layout model).

Which extensions can be learned online (``ONLINE_EXTENSIONS``): those of the twist stage whose
formula depends on the wheel speeds and the base twist only (speed_slip, direction_asymmetry,
lateral_skid, icr_offset, ratio_yaw_slip), acceleration_slip, and the residual model, whose
gains are learned with its coefficients held (the offline regression's terms and coefficients,
scaled to the current ground). The others need what a learning segment does not carry: the time
since the drive started (terrain_regime), or a state carried across the segment's start (the
lags, time_offset, the backlash's play per wheel); the sparse correction has nothing of its own
to learn (no gain; its terms and coefficients come from a regression over a whole drive). A
configuration with one of them is refused with that reason.

**acceleration_slip and the residual model's rate terms** read the base twist's rate at each
wheel sample, which the 50 ms blocks of a learning segment lose. A layout with one in use
(:attr:`LayoutModel.paired`) keeps every wheel step in its segments, each as a pair of
columns: the wheel speeds one second earlier at the step's wheel-speed rate (the node's rule:
the difference to the step before over their start stamps' distance, 0 after a break), with
zero duration, then the step itself. The layout model reads a pair as two samples one second
apart (:meth:`BoundAugmented.intervals`: the rate is the difference of the base twists, the
node's, exact for a base model linear in the wheel speeds) and gives the first column no twist,
so the calibrator's rollouts, Jacobian and noise bases run on such segments unchanged. The
extensions (and their partials) run on the second columns only, half the columns; the numbers
are the pair intervals' bit for bit (:meth:`LayoutModel.twist`, :func:`_paired_gradient`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Mapping

import numpy as np

from skidkin_ros.core.calibration.engine import BASE, ParameterLayout
from skidkin_ros.core.calibration.fitting import segment_errors, segment_errors_jacobian
from skidkin_ros.core.calibration.noise_fit import (mahalanobis, segment_covariances,
                                                    segment_motion, SegmentMotion)
from skidkin_ros.core.calibration.segments import SegmentSet
from skidkin_ros.core.kinematics.augmented import BoundAugmented, rate_divisor
from skidkin_ros.core.kinematics.augmented_tangents import (base_tangents, chain_partials,
                                                            interval_tangents)
from skidkin_ros.core.kinematics.extensions import get_extension
from skidkin_ros.core.kinematics.models import BoundModel, get_model, KinematicModel
from skidkin_ros.core.kinematics.scalar_tangents import scalar_tangents, ScalarTangents
from skidkin_ros.core.kinematics.specs import Geometry
from skidkin_ros.core.odometry.reference import ONLINE_EXTENSIONS, rate_extensions
from skidkin_ros.core.odometry.residual_uncertainty import RESIDUAL_EXTENSION, ResidualUncertainty
from skidkin_ros.core.odometry.uncertainty import ParameterUncertainty
from skidkin_ros.core.online.calibrator import OnlineCalibrator
from skidkin_ros.core.online.gates import _Ref
from skidkin_ros.core.online.grounds import Ground
from skidkin_ros.core.online.steps import CHAIN, LEFT, RIGHT, T0
from skidkin_ros.core.online.window import _stack

__all__ = ['LayoutModel', 'LayoutUncertainty', 'AugmentedCalibrator', 'PairedSegmentSet',
           'ONLINE_EXTENSIONS']

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
        # an extension reads the base twist's rate: segments come as pairs (module docstring)
        _, ext_values = layout.values(layout.vector())
        self.paired = bool(rate_extensions(layout.extensions, {
            f'augmented.{ext}.{name}': value for ext, named in ext_values.items()
            for name, value in named.items()}))

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
        if not self.paired:
            return np.asarray(self.source(k).twist(omega_l, omega_r), dtype=float)
        left, right, shape = _rows(omega_l, omega_r)
        bound = self.source(k)
        base = np.asarray(bound.base.twist(left, right), dtype=float)
        # BoundAugmented.intervals of the pairs (_pair_steps), on the second columns only:
        # their rate is the difference of the pair's base twists over 1 s, the first column
        # only gives the rate (no twist)
        odd = (slice(None), slice(1, None, 2))
        first = (slice(None), slice(0, left.shape[1] - 1, 2))   # a last lone column: no pair
        rate = (base[odd] - base[first]) / 1.0
        twist = np.zeros(base.shape)
        twist[odd] = bound.memoryless(left[odd], right[odd], np.zeros(left[odd].shape), rate,
                                      base[odd])
        return twist.reshape(shape + (3,))

    def twist_gradient(self, k: np.ndarray, geometry: Geometry, omega_l: np.ndarray,
                       omega_r: np.ndarray) -> np.ndarray:
        """Return d twist / d k (..., 3, p), exact: :func:`interval_tangents` of the twist.

        :meth:`twist` is the bound model's memoryless twist at the drive start (rate 0, no
        lag state), so the tangents are those of one-sample intervals at t = 0 with a zero
        step: the base model's gradient carried through each extension's partials, the
        diagnosis's own forward mode.
        """
        left, right, shape = _rows(omega_l, omega_r)
        if self.paired:
            return _paired_gradient(self.source(k), left, right,
                                    self.layout.free).reshape(shape + (3, -1))
        still = np.zeros(left.shape, dtype=np.int64)
        dt_s, restart = np.zeros(left.shape), np.zeros(left.shape, dtype=bool)
        # the tangents may live in the work arrays of base_tangents: stacked into a new array
        _, tangents = interval_tangents(self.source(k), still, left, right, dt_s, restart,
                                        self.layout.free)
        out = np.moveaxis(np.stack(tangents), (0, 1), (-2, -1))
        return out.reshape(shape + (3, -1))

    def file_values(self, k: np.ndarray) -> dict[str, float]:
        """Return the flat parameters-file entries of ``k`` (models.<base>.*, augmented.*)."""
        base_values, ext_values = self.layout.values(np.asarray(k, dtype=float))
        out = {f'models.{self.base.name}.{name}': value for name, value in base_values.items()}
        for ext, values in ext_values.items():
            out.update({f'augmented.{ext}.{name}': value for name, value in values.items()})
        return out


def _rows(omega_l, omega_r) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
    """Return the wheel speeds as (D, L) rows (one row unless 2-D) and their shape."""
    omega_l = np.asarray(omega_l, dtype=float)
    omega_r = np.asarray(omega_r, dtype=float)
    shape = np.broadcast_shapes(omega_l.shape, omega_r.shape)
    rows = (1, -1) if len(shape) != 2 else shape
    return (np.broadcast_to(omega_l, shape).reshape(rows),
            np.broadcast_to(omega_r, shape).reshape(rows), shape)


def _paired_gradient(bound: BoundAugmented, left: np.ndarray, right: np.ndarray,
                     free: tuple[tuple[int, int], ...]) -> np.ndarray:
    """Return d twist / dk (D, 2L, 3, P) of (D, 2L) pairs, on the second columns only.

    :func:`interval_tangents`' forward mode over the pairs (:func:`_pair_steps`), each
    extension's partials evaluated where a twist is (the first column of a pair only gives the
    rate, and has none): half the columns. The rate's tangents are the difference of the
    pair's base tangents over 1 s, as the rate is (twist-stage extensions only: the online
    ones).
    """
    odd = (slice(None), slice(1, None, 2))
    last = left.shape[1] - 1   # a last lone column (an odd width) has no pair: no twist
    base = np.asarray(bound.base.twist(left, right), dtype=float)
    d_base = base_tangents(bound.base, left, right, free)
    d_x = [d[:, :, 1::2].copy() for d in d_base]
    d_rate = [(d[:, :, 1::2] - d[:, :, 0:last:2]) / 1.0 for d in d_base]
    x = base[odd]
    rate = (base[odd] - base[:, 0:last:2]) / 1.0
    wheels = left[odd], right[odd]
    t_s = np.zeros(wheels[0].shape)
    live = any(i < 0 for i, _ in free)
    for index, (name, k) in enumerate(zip(bound.extensions, bound.values)):
        ext = get_extension(name)
        mine = [(c, j) for c, (i, j) in enumerate(free) if i == index]
        d_twist, d_by_rate, d_k = ext.partials(k, x, *wheels, t_s, rate, [j for _, j in mine],
                                               inputs=live)
        d_x, live = chain_partials((d_twist, d_by_rate, d_k), d_x, d_rate, mine, live)
        x = ext.apply(k, x, *wheels, t_s, rate)
    out = np.zeros(base.shape + (len(free),))
    out[odd] = np.moveaxis(np.stack(d_x), (0, 1), (-2, -1))
    return out


def _pair_steps(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return stamps, steps and restarts that read (D, L) columns as pairs one second apart.

    Even columns start afresh (rate 0) and step 1 s to the odd column after them, whose rate is
    then the difference of the two base twists (:func:`twist_rates`).
    """
    dt_s = np.zeros(shape)
    dt_s[:, ::2] = 1.0
    restart = np.zeros(shape, dtype=bool)
    restart[:, ::2] = True
    return np.zeros(shape, dtype=np.int64), dt_s, restart


class PairedSegmentSet(SegmentSet):
    """Learning segments whose steps come as pairs of columns (the module docstring).

    The first column of a pair has zero duration; the steps counted (what the rollouts' widths
    are cut to) reach the last pair's second column.
    """

    @property
    def step_counts(self) -> np.ndarray:
        moving = self.dt_s > 0.0
        last = moving.shape[1] - np.argmax(moving[:, ::-1], axis=1)
        return np.where(moving.any(axis=1), last, 0)


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
        errors = segment_errors(self.model, ground.k, self.geometry, batch)
        # the sensitivity is d (predicted end pose) / dk: minus that of the error (true - pred)
        sens = segment_errors_jacobian(self.model, ground.k, self.geometry, batch)
        return errors, sens * -self.scale

    def _segment(self, a: _Ref, b: _Ref) -> SegmentSet | None:
        """Return the segment a -> b; for a paired layout, every step as a pair of columns."""
        if not self.model.paired:
            return super()._segment(a, b)
        span = self._steps.span(a.t_ns, b.t_ns)
        if span is None:
            return None
        i0, i1 = span
        first = max(i0 - 1, 0)   # the step before: the first step's rate
        rows = self._steps.rows[first:i1 + 1]
        count = len(rows)
        t0 = np.fromiter((row[T0] for row in rows), np.int64, count)
        chain = np.fromiter((row[CHAIN] for row in rows), np.int64, count)
        t1 = np.array(self._steps.t1[first:i1 + 1], dtype=np.int64)
        speeds = [np.fromiter((row[side] for row in rows), float, count)
                  for side in (LEFT, RIGHT)]
        # the node's rate: the difference to the step before over their start stamps' distance
        step = np.diff(t0) * 1e-9
        usable = (step > 0.0) & (chain[1:] == chain[:-1])
        safe = rate_divisor(step, usable)
        rates = [np.where(usable, np.diff(w) / safe, 0.0) for w in speeds]
        skip = i0 - first
        dt_s = (np.minimum(t1, b.t_ns) - np.maximum(t0, a.t_ns))[skip:] * 1e-9
        if dt_s.max() > self.options.max_gap_s:
            return None
        width = 2 * dt_s.size
        pairs = [np.empty(width) for _ in range(2)]
        for pair, w, rate in zip(pairs, speeds, rates):
            pair[1::2] = w[skip:]
            pair[::2] = w[skip:] - (rate[skip - 1:] if skip else np.r_[0.0, rate])
        steps = np.zeros(width)
        steps[1::2] = dt_s
        return PairedSegmentSet(
            drive=np.zeros(1, dtype=int), t_a_ns=np.array([a.t_ns], np.int64),
            t_b_ns=np.array([b.t_ns], np.int64), start=np.array([[a.x, a.y, a.yaw]]),
            end=np.array([[b.x, b.y, b.yaw]]), omega_l=pairs[0][None], omega_r=pairs[1][None],
            dt_s=steps[None], path_m=np.array([b.path_m - a.path_m]))

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

    # The file's residual-model coefficient covariance (coefficients held: it stays as loaded;
    # set by the maker, None: none).
    coefficient_covariance: np.ndarray | None = None

    def uncertainty(self) -> ParameterUncertainty | None:
        k, covariance = self.in_force()   # the active ground's, or the blend while holding
        coefficients = None
        layout = self.model.layout
        if self.coefficient_covariance is not None and RESIDUAL_EXTENSION in layout.extensions:
            _, ext_k = layout.parameters(k)
            coefficients = ResidualUncertainty.of(
                ext_k[layout.extensions.index(RESIDUAL_EXTENSION)], self.coefficient_covariance)
        return LayoutUncertainty.of_layout(self.model, k, self.geometry, covariance, coefficients)


@dataclass(frozen=True)
class LayoutUncertainty(ParameterUncertainty):
    """The parameter uncertainty of a layout model, carried per wheel sample on floats.

    d(twist)/dk_j at the step's wheel speeds (and their rate), exact, in one forward-mode pass
    on floats (:class:`~skidkin_ros.core.kinematics.scalar_tangents.ScalarTangents`: the base
    model's gradient through each extension's float partials) where the layout is covered (a
    linear base; the residual model with only its gains learned). Otherwise the central
    difference of the augmented twist (as :class:`ParameterUncertainty` takes it for a model not
    linear in the wheel speeds), with the 2p perturbed models bound once per parameter vector
    and evaluated on plain floats (:meth:`BoundAugmented.scalar_memoryless`). At 1 kHz with a
    residual model of eight learned parameters the differences cost about 190 us per sample,
    the exact pass about 20.
    """

    # per parameter: (model at k + h, model at k - h, 1 / 2h); () where ``tangents`` is used
    pairs: tuple = ()
    # a layout whose twist reads the rate (or that carries coefficients): the base model's
    # pseudo-inverse (2 x 3 floats) that turns the state's base twist and rate back into wheel
    # speeds and their rate; else None
    wheels_of: tuple | None = None
    # the residual model's held coefficients' uncertainty (the file's), carried after the
    # learned parameters (their covariance is the block after the learned one); None: none
    coefficients: ResidualUncertainty | None = None
    # the exact float tangents (None: not covered, the central differences of ``pairs``)
    tangents: ScalarTangents | None = None

    @property
    def size(self) -> int:
        extra = 0 if self.coefficients is None else self.coefficients.size
        return len(self.nonlinear[1]) + extra

    @classmethod
    def of_layout(cls, model: LayoutModel, k: np.ndarray, geometry: Geometry,
                  covariance: np.ndarray, coefficients: ResidualUncertainty | None = None
                  ) -> 'LayoutUncertainty | None':
        """Return the uncertainty of ``model`` at ``k`` (None: nothing to carry).

        ``coefficients``: the residual model's held coefficients' uncertainty, carried too
        (from the step's state: only on a base model linear in the wheel speeds).
        """
        k = np.asarray(k, dtype=float)
        covariance = np.asarray(covariance, dtype=float)
        if k.size == 0 or not np.any(covariance):
            return None
        linear = type(model.base).rows is not KinematicModel.rows
        if coefficients is not None and linear:
            size = k.size + coefficients.size
            joint = np.zeros((size, size))
            joint[:k.size, :k.size] = covariance
            joint[k.size:, k.size:] = coefficients.covariance
            covariance = joint
        else:
            coefficients = None
        pairs = []
        tangents = scalar_tangents(model.source(k), model.layout.free)
        for j in range(k.size if tangents is None else 0):
            step = REL_STEP * max(abs(float(k[j])), 1.0)
            plus, minus = k.copy(), k.copy()
            plus[j] += step
            minus[j] -= step
            pairs.append((model.source(plus), model.source(minus), 1.0 / (2.0 * step)))
        wheels_of = None
        if (model.paired or coefficients is not None) and linear:
            rows = model.base.rows(model.layout.parameters(k)[0], geometry)
            wheels_of = tuple(np.linalg.pinv(np.asarray(rows, dtype=float)).ravel().tolist())
        return cls(covariance, (), (model, tuple(k.tolist()), geometry, REL_STEP), tuple(pairs),
                   wheels_of, coefficients, tangents)

    def pose_covariance(self, sens) -> tuple[float, ...]:
        """Upper triangle of S Sigma_k S^T for S given as p columns, one product at a time.

        The p columns as one (p, 3) array A: A^T (Sigma_k A), one array fewer to build than
        the base form's; read once per wheel sample, equal to it to rounding (the file's
        covariance keeps the base form, bit for bit as it was).
        """
        s = np.array(sens, dtype=float)   # (p, 3)
        (c00, c01, c02), (_, c11, c12), (_, _, c22) = (s.T @ (self.covariance @ s)).tolist()
        return c00, c01, c02, c11, c12, c22

    def state_jacobian(self, state) -> list[tuple[float, float, float]] | None:
        """Return d(twist)/dk at the step's source state, rate terms included (None: not used).

        For a layout whose twist reads the base twist's rate (the residual model's rate terms,
        acceleration_slip) the wheel speeds alone do not give the twist: the state's base
        twist and rate (at the parameters in force) are turned back into the wheel speeds and
        their rate (the base model is linear in them: the pseudo-inverse recovers them), and
        each perturbed model takes its own base twist and rate of those. The held
        coefficients' columns follow (:meth:`ResidualUncertainty.jacobian`, the node's rule for
        a file's coefficient covariance). Other layouts: None (:meth:`twist_jacobian`).
        """
        if self.wheels_of is None or state is None:
            return None
        a0, a1, a2, b0, b1, b2 = self.wheels_of
        (v0, v1, v2), (r0, r1, r2) = state.b, state.r
        left, right = a0 * v0 + a1 * v1 + a2 * v2, b0 * v0 + b1 * v1 + b2 * v2
        rate_l, rate_r = a0 * r0 + a1 * r1 + a2 * r2, b0 * r0 + b1 * r1 + b2 * r2
        tangents = self.tangents
        out = [] if tangents is None else tangents.jacobian(left, right, rate_l, rate_r)
        for plus, minus, inverse in self.pairs:
            a = plus.scalar_memoryless(left, right, 0.0, plus.base.scalar_twist(rate_l, rate_r),
                                       plus.base.scalar_twist(left, right))
            b = minus.scalar_memoryless(left, right, 0.0,
                                        minus.base.scalar_twist(rate_l, rate_r),
                                        minus.base.scalar_twist(left, right))
            out.append(((a[0] - b[0]) * inverse, (a[1] - b[1]) * inverse,
                        (a[2] - b[2]) * inverse))
        if self.coefficients is not None:
            out.extend(self.coefficients.jacobian(state))
        return out

    def twist_jacobian(self, vx: float, vy: float, w: float,
                       wheels: tuple[float, float] | None = None
                       ) -> list[tuple[float, float, float]] | None:
        if wheels is None:
            return None
        left, right = wheels
        out = [] if self.tangents is None else self.tangents.jacobian(left, right)
        for plus, minus, inverse in self.pairs:
            a = plus.scalar_memoryless(left, right, 0.0)
            b = minus.scalar_memoryless(left, right, 0.0)
            out.append(((a[0] - b[0]) * inverse, (a[1] - b[1]) * inverse,
                        (a[2] - b[2]) * inverse))
        if self.coefficients is not None:
            # the held coefficients' slopes need the step's state (state_jacobian): none here
            out.extend([(0.0, 0.0, 0.0)] * self.coefficients.size)
        return out
