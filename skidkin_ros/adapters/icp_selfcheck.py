"""Which kiss-icp settings a recording gets: the fast ones only where kiss-icp's own agree.

The fast settings (:class:`~skidkin_ros.adapters.lidar_gt.IcpConfig`'s defaults: a voxel from
the data, convergence 1e-3) were chosen on the project's own scenes. On a scene they were not
tuned for (a sparse snow field, a corridor) they may register worse than kiss-icp's defaults
(a voxel of max_range / 100, convergence 1e-4), and nothing in the fast result says so: a
registration that slides along a corridor is as smooth as one that does not. So every
recording checks them on a sample of itself, and no scene pays for another's tuning.

Recipe (:func:`plan_samples`, :func:`compare_motion`, :func:`choose`):

1. **Sample**: a few windows of ``window_s`` spread over the recording, each at the END of a
   chunk's own part, where the fast registration of that chunk has run longest (a
   registration that loses itself over a long chunk does so late, not early). Each window is
   registered from scratch with the reference settings (kiss-icp's defaults), preceded by
   ``warmup_s`` that is not compared (the reference's map is empty at its start). The sample
   tasks run in the same pool as the fast chunks, so on several cores they cost little wall
   time.
2. **Compare** the motions, not the poses (the two registrations start in different frames):
   for every frame both registered in a window, the rigid motion over ``horizon_s`` to a later
   frame, in the first frame's body frame, must agree within ``abs_m`` + ``rel`` x the
   distance and ``abs_rad`` + ``rel`` x the turn. Loose enough for two registrations' own
   noise (on the sparse snow field both err by 6-7 cm median over 1 s, and they differ by
   14 cm at the 90th percentile), tight enough for one that slid, and no motion may differ by
   more than ``gross_m`` (a registration that jumped, even once).
3. **Choose**: the fast settings are kept when at least ``min_agree`` of the compared motions
   agree in every window, none grossly; otherwise the whole recording is registered with the
   reference settings (the chunks of the fast run are dropped). A recording too short for a
   window, or
   a user who set the voxel size, the convergence or the points per voxel, skips the check.
   Where the voxel from the data is finer than kiss-icp's (:func:`finer_than_reference`), the
   fast settings are not faster, and kiss-icp's defaults are used without a check.

The sample registrations are cached like any chunk (their windows and settings are in the key),
so a second run of the same recording repeats the same choice without registering anything.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import math
from typing import Sequence

import numpy as np

from skidkin_ros.adapters.lidar_gt import IcpConfig, Registration
from skidkin_ros.core.timeunits import s_to_ns
from skidkin_ros.errors import ParameterError

__all__ = ['Agreement', 'SelfCheckOptions', 'SettingsChoice', 'check_samples', 'choose',
           'compare_motion', 'finer_than_reference', 'is_automatic', 'plan_samples',
           'reference_config']

# kiss-icp's own defaults (kiss_icp.config: voxel max_range / 100, convergence 1e-4).
_KISS_CONVERGENCE = 1e-4
_KISS_POINTS_PER_VOXEL = 20
_KISS_ITERATIONS = 500
# One sample window per this many seconds of recording (at least one).
_SECONDS_PER_WINDOW = 100.0


@dataclass(frozen=True)
class SelfCheckOptions:
    """How the fast settings are checked (module docstring); ``enabled`` False: no check.

    ``windows``: sample windows; ``window_s`` / ``warmup_s``: compared and uncompared length of
    each (s); ``horizon_s``: the motion compared (s); ``abs_m``, ``abs_rad``, ``rel``: its
    tolerance; ``min_agree``: the share of motions that must agree in every window;
    ``gross_m``: the largest difference any motion may have.
    """

    enabled: bool = True
    windows: int = 3
    window_s: float = 8.0
    warmup_s: float = 2.0
    horizon_s: float = 1.0
    abs_m: float = 0.15
    abs_rad: float = 0.03
    rel: float = 0.1
    min_agree: float = 0.8
    gross_m: float = 0.5

    def __post_init__(self) -> None:
        if not isinstance(self.windows, int) or self.windows < 1:
            raise ParameterError(f'self-check windows must be a whole number >= 1, got '
                                 f'{self.windows!r}')
        for name in ('window_s', 'horizon_s', 'abs_m', 'abs_rad', 'gross_m'):
            if not getattr(self, name) > 0.0:
                raise ParameterError(f'SelfCheckOptions.{name} must be > 0, got '
                                     f'{getattr(self, name)}')
        if not self.horizon_s < self.window_s:
            raise ParameterError('SelfCheckOptions.horizon_s must be shorter than window_s')
        if self.warmup_s < 0.0 or self.rel < 0.0 or not 0.0 < self.min_agree <= 1.0:
            raise ParameterError('SelfCheckOptions: need warmup_s >= 0, rel >= 0 and '
                                 '0 < min_agree <= 1')


def is_automatic(config: IcpConfig) -> bool:
    """Tell whether the settings are the fast defaults, voxel unresolved (else: kept as set)."""
    default = IcpConfig()
    return (config.voxel_size_m is None and config.convergence == default.convergence
            and config.max_points_per_voxel == default.max_points_per_voxel
            and config.max_iterations == default.max_iterations)


def reference_config(config: IcpConfig) -> IcpConfig:
    """Return kiss-icp's default registration settings with this config's input checks.

    Ranges, deskew, stride, threads and the input checks stay; the voxel (max_range / 100, as
    ``kiss_icp.config.load_config`` sets it), the convergence, the iterations and the points
    per voxel become kiss-icp's own.
    """
    return replace(config, voxel_size_m=round(config.max_range_m / 100.0, 6),
                   convergence=_KISS_CONVERGENCE, max_points_per_voxel=_KISS_POINTS_PER_VOXEL,
                   max_iterations=_KISS_ITERATIONS)


def finer_than_reference(config: IcpConfig, reference: IcpConfig) -> bool:
    """Tell whether the data's voxel is finer than kiss-icp's: then the defaults are used.

    The fast settings save time with a coarser voxel than kiss-icp's and a looser convergence;
    with a finer voxel (a dense scan: 0.55 m in the courtyard against kiss-icp's 1 m) they cost
    twice kiss-icp's CPU time per scan, and were no more accurate there (3.1 cm against 2.9 cm
    over 1 s, lab/bench/gt_scenes.py), so kiss-icp's defaults are used without a check.
    """
    return (config.voxel_size_m is not None and reference.voxel_size_m is not None
            and config.voxel_size_m < reference.voxel_size_m)


def plan_samples(stops_ns: Sequence[int | None], start_ns: int, end_ns: int,
                 options: SelfCheckOptions) -> list[tuple[int, int | None]]:
    """Return the sample windows [start, stop) in receive time (ns): one per 100 s recorded.

    At most ``options.windows``, at least one: the sample stays near a tenth of the recording.

    ``stops_ns``: where each chunk's own part ends (None: the open last chunk, whose window
    starts so that it ends at ``end_ns``, an estimate of the last lidar receive time, and is
    left open); ``start_ns``: the first lidar receive time. Windows end at the chunks' ends,
    taken evenly over the chunks, the last chunk always included.
    """
    length_ns = s_to_ns(options.window_s + options.warmup_s)
    span_s = (int(end_ns) - int(start_ns)) * 1e-9
    count = max(1, min(options.windows, len(stops_ns), int(span_s // _SECONDS_PER_WINDOW)))
    picks = sorted({int(round(i)) for i in np.linspace(len(stops_ns) - 1, 0, count)})
    windows: list[tuple[int, int | None]] = []
    for k in picks:
        stop = stops_ns[k]
        windows.append(((int(end_ns) if stop is None else int(stop)) - length_ns,
                        None if stop is None else int(stop)))
    return windows


@dataclass(frozen=True)
class Agreement:
    """How two registrations of one window agree: motions compared, agreeing, the worst."""

    window: tuple[int, int | None]
    compared: int
    agreeing: int
    worst_m: float
    worst_rad: float

    @property
    def share(self) -> float:
        return self.agreeing / self.compared if self.compared else 0.0

    def text(self) -> str:
        return (f'{self.agreeing} of {self.compared} motions agree (worst {self.worst_m:.3f} m, '
                f'{self.worst_rad:.4f} rad)')


def _rotation_angle(rotation: np.ndarray) -> float:
    return math.acos(max(-1.0, min(1.0, (float(np.trace(rotation)) - 1.0) / 2.0)))


def compare_motion(fast: Registration, reference: Registration,
                   window: tuple[int, int | None], options: SelfCheckOptions) -> Agreement:
    """Compare the motions over ``horizon_s`` of two registrations in a window (step 2).

    Frames are matched by their end stamp; the window's first ``warmup_s`` is not compared.
    """
    compare_from = window[0] + s_to_ns(options.warmup_s)
    compare_to = np.iinfo(np.int64).max if window[1] is None else window[1]
    fast_rows = {int(e): i for i, e in enumerate(fast.end_ns) if fast.registered[i]}
    common = [(int(e), fast_rows[int(e)], j) for j, e in enumerate(reference.end_ns)
              if reference.registered[j] and int(e) in fast_rows
              and compare_from <= int(e) < compare_to]
    ends = np.array([c[0] for c in common], dtype=np.int64)
    horizon_ns = s_to_ns(options.horizon_s)
    compared = agreeing = 0
    worst_m = worst_rad = 0.0
    for a in range(len(common)):
        b = int(np.searchsorted(ends, ends[a] + horizon_ns))
        if b >= len(common) or ends[b] - ends[a] > 1.5 * horizon_ns:
            continue
        m_fast = np.linalg.inv(fast.lidar_pose[common[a][1]]) @ fast.lidar_pose[common[b][1]]
        m_ref = (np.linalg.inv(reference.lidar_pose[common[a][2]])
                 @ reference.lidar_pose[common[b][2]])
        moved = float(np.linalg.norm(m_ref[:3, 3]))
        turned = _rotation_angle(m_ref[:3, :3])
        err_m = float(np.linalg.norm(m_fast[:3, 3] - m_ref[:3, 3]))
        err_rad = _rotation_angle(m_fast[:3, :3].T @ m_ref[:3, :3])
        compared += 1
        if (err_m <= options.abs_m + options.rel * moved
                and err_rad <= options.abs_rad + options.rel * turned):
            agreeing += 1
        worst_m, worst_rad = max(worst_m, err_m), max(worst_rad, err_rad)
    return Agreement(window, compared, agreeing, worst_m, worst_rad)


@dataclass(frozen=True)
class SettingsChoice:
    """The settings chosen for a recording and why (one Agreement per sample window)."""

    config: IcpConfig
    kept_fast: bool
    agreements: tuple[Agreement, ...] = ()
    reason: str = ''
    notes: tuple[str, ...] = field(default=())

    def note(self) -> str:
        """Return the one-line account for the user."""
        if not self.agreements:
            return f'kiss-icp settings not self-checked: {self.reason}'
        detail = '; '.join(a.text() for a in self.agreements)
        if self.kept_fast:
            scans = (f', one scan in {self.config.stride}' if self.config.stride > 1 else '')
            return (f'kiss-icp settings self-check: the fast settings (voxel '
                    f'{self.config.voxel_size_m:g} m, convergence {self.config.convergence:g}'
                    f"{scans}) agree with kiss-icp's defaults on every scan of "
                    f'{len(self.agreements)} sample window(s): {detail}; kept')
        return (f"kiss-icp settings self-check: the fast settings disagree with kiss-icp's "
                f'defaults ({detail}); the recording is registered with the defaults (voxel '
                f'{self.config.voxel_size_m:g} m, convergence {self.config.convergence:g}, '
                f'every scan), slower')


def choose(fast: IcpConfig, reference: IcpConfig, agreements: Sequence[Agreement],
           options: SelfCheckOptions) -> SettingsChoice:
    """Keep the fast settings when every window agrees well enough (step 3)."""
    agreements = tuple(agreements)
    if not agreements:
        return SettingsChoice(fast, True, (), 'no sample window')
    keep = all(a.compared > 0 and a.share >= options.min_agree and a.worst_m <= options.gross_m
               for a in agreements)
    return SettingsChoice(fast if keep else reference, keep, agreements)


def check_samples(fast_parts: Sequence[Registration | None],
                  samples: Sequence[tuple[tuple[int, int | None], Registration | None]],
                  fast: IcpConfig, reference: IcpConfig,
                  options: SelfCheckOptions) -> SettingsChoice:
    """Compare each sample window with the fast chunk that registered it; choose (step 3).

    ``fast_parts``: the fast registration of every chunk (None: the chunk failed);
    ``samples``: (window, reference registration or None when that task failed). A window
    whose reference or fast registration is missing is not judged; when no window can be
    judged, the fast settings stay, with the reason.
    """
    agreements = []
    for window, sample in samples:
        if sample is None:
            continue
        best: Agreement | None = None
        for part in fast_parts:
            if part is None:
                continue
            agreement = compare_motion(part, sample, window, options)
            if best is None or agreement.compared > best.compared:
                best = agreement
        if best is not None and best.compared:
            agreements.append(best)
    if not agreements:
        return SettingsChoice(fast, True, (), 'no sample window could be compared (a sample '
                              'or its chunk failed, or the recording is too short)')
    return choose(fast, reference, agreements, options)
