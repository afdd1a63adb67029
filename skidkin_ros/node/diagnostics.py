"""The node's /diagnostics status: level and summary from the counts of the last period.

Every sample the node receives is counted by what happened to it (the odometer's causes plus the
node's own: 'received', 'missing_joint', 'waiting_for_clock', 'set_pose_rejected', ...). Once a
second the counts since the previous status decide the level: STALE while no sample was accepted
within ``input_timeout``, ERROR for any cause in :data:`ERROR_CAUSES`, WARN for any in
:data:`WARN_CAUSES`, OK otherwise. The status carries the model, rates, ages and every count.
"""

from __future__ import annotations

import collections
import time
from typing import Mapping

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from skidkin_ros.core.odometry.config import OdometryConfig
from skidkin_ros.core.odometry.integrator import SampleStatus
from skidkin_ros.core.timeunits import NS_PER_S

__all__ = ['WARN_CAUSES', 'ERROR_CAUSES', 'StatusReport']

# Counter names reported on /diagnostics; which of them make the status WARN or ERROR.
WARN_CAUSES = ('non_finite', 'implausible', 'wheel_jump', 'older', 'gap', 'zero_stamp',
               'negative_stamp', 'future_stamp', 'stamp_step_back', 'stamp_reset', 'missing_joint',
               'duplicate_joint', 'malformed_message', 'unpaired', 'waiting_for_clock',
               'set_pose_rejected', 'imu_non_finite', 'imu_saturated', 'imu_older',
               'imu_bad_stamp', 'imu_future_stamp', 'imu_no_rate', 'imu_interval_stale',
               'reference_non_finite', 'reference_bad_stamp', 'reference_older',
               'reference_frame', 'reference_jump', 'reference_stall', 'online_inconsistent',
               'online_nonfinite', 'reference_future',
               'stale_position', 'position_range', 'imu_clock_reset',
               'imu_interval_contradicts', 'imu_interval_clock_ahead')
ERROR_CAUSES = ('non_finite_state', 'non_finite_output', 'callback_error')


class StatusReport:
    """Builds one DiagnosticStatus per period from the node's counters (steady clock)."""

    def __init__(self) -> None:
        self._counters_at_start: collections.Counter[str] = collections.Counter()
        self._start_mono_ns = time.monotonic_ns()

    def status(self, name: str, config: OdometryConfig, counters: collections.Counter[str],
               stale: bool, age_s: float | None,
               side_ages_s: Mapping[str, float | None] | None = None,
               wheel_signal: str = 'velocity',
               imu: Mapping[str, float] | None = None,
               online: Mapping[str, float | str] | None = None) -> DiagnosticStatus:
        """Return the status of the period since the last call, and start a new period.

        ``age_s``: steady-clock age of the last accepted sample (None: none yet);
        ``side_ages_s``: the same per wheel topic (wheel_topics input only); ``wheel_signal``:
        the signal (velocity or position) that measured the last interval; ``imu``: the gyro
        filter's state (gain, bias, their sigmas, ...) when imu.mode is not off; ``online``:
        the online calibration's state, parameters and sigmas when online.enabled.
        """
        now = time.monotonic_ns()
        period_s = max((now - self._start_mono_ns) / NS_PER_S, 1e-9)
        recent = counters - self._counters_at_start
        self._counters_at_start = collections.Counter(counters)
        self._start_mono_ns = now
        level, summary = _level(recent, stale)
        if imu is not None and level != DiagnosticStatus.STALE and imu.get('contradicts_wheels'):
            level = max(level, DiagnosticStatus.WARN)
            ratio = imu.get('turn_ratio', 0.0)
            summary = (f'the gyro contradicts the wheels (it turns {ratio:.3g}'
                       ' times what the model says): not used, the model runs alone; check the '
                       'IMU mounting (z up) and its unit (rad/s)')
        elif imu is not None and level == DiagnosticStatus.OK and imu.get('at_bound'):
            level = DiagnosticStatus.WARN
            summary = ('imu gain at its bound (imu.adapt.gain_min/gain_max): the model or the '
                       'gyro calibration is far off')
        status = DiagnosticStatus(level=level, name=name, message=summary,
                                  hardware_id=config['robot'])
        values = {
            'model': config.model,
            'interval': config['interval'],
            'input': config['input'],
            'wheel_signal': f'{config["wheel_signal"]} (in use: {wheel_signal})',
            'covariance': 'calibrated' if config.active_noise else 'fallback',
            'rate_hz': f'{recent["published"] / period_s:.2f}',
            'accepted_rate_hz': f'{_accepted(recent) / period_s:.2f}',
            'last_sample_age_s': _age(age_s),
        }
        for side, side_age in (side_ages_s or {}).items():
            values[f'{side}_age_s'] = _age(side_age)
        values['imu.mode'] = config['imu.mode']
        for key, value in (imu or {}).items():
            values[f'imu.{key}'] = f'{value:.6g}'
        for key, value in (online or {}).items():
            values[f'online.{key}'] = value if isinstance(value, str) else f'{value:.6g}'
        for cause in sorted(counters):
            values[f'count.{cause}'] = str(counters[cause])
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        return status


def _age(age_s: float | None) -> str:
    return 'none' if age_s is None else f'{age_s:.3f}'


def _accepted(counts: collections.Counter[str]) -> int:
    return sum(counts[s.value] for s in SampleStatus if s.accepted)


def _level(recent: collections.Counter[str], stale: bool) -> tuple[bytes, str]:
    errors = {c: recent[c] for c in ERROR_CAUSES if recent[c]}
    warnings = {c: recent[c] for c in WARN_CAUSES if recent[c]}
    if stale:
        return DiagnosticStatus.STALE, 'no wheel input within input_timeout: pose held'
    if errors:
        return DiagnosticStatus.ERROR, f'errors in the last period: {errors}'
    if warnings:
        return DiagnosticStatus.WARN, f'samples rejected in the last period: {warnings}'
    return DiagnosticStatus.OK, 'integrating'
