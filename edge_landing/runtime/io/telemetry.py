"""Telemetry samples matched to a frame's capture time, with the trust rules of ARCHITECTURE.md §12.

The link thread calls ``add_*`` as messages arrive; the pipeline asks ``lookup(capture_time_s, now_s)``.

- Clock: autopilot timestamps (``time_boot_ms``) are mapped onto this computer's monotonic clock by
  :class:`ClockOffset`, a windowed jitter correction like ArduPilot's (GCS_Common.cpp, JitterCorrection): the
  offset follows the fastest sample, is re-estimated from the fastest sample of every window (so a drifting
  autopilot clock never loses telemetry for good) but rises by no more than the clocks can drift apart
  (``max_drift``), and a sample stamped from the future by more than ``max_future_s`` is dropped. A late sample
  keeps its own (old) time, so telemetry held back and delivered in a burst is not matched to frames captured
  after it was measured (``clock_offset.py``). A sample no newer than the last of its kind is dropped.
- Plausibility: every field is gated (non-finite, tilt beyond the envelope, yaw out of range, negative or
  too large height above ground, a rangefinder outside its own range); a rejected sample is counted by
  reason and never used. Nothing here raises on a bad number.
- Frame moves: a local position farther from the last one than the vehicle can fly (``max_speed_mps``; an EKF
  reset, a GPS glitch) or, when the samples carry the autopilot's velocity, farther from where that velocity
  carried the last one than flying allows (a metre or more: a small reset, ``position_resets.py``), a heading
  that turned faster than it can yaw (an EKF yaw reset) or a reboot (its clock restarted, or ``forget``) starts
  a new ``position_epoch`` (VehicleState): samples from before are dropped, and fusion and the committed spot,
  which live in local NED, start over.
- Freshness: a match is fresh only when the newest accepted attitude arrived no longer than ``fresh_s``
  ago on the companion's clock.
- Round trips: when the autopilot answers TIMESYNC, its answers cap the clock offset (telemetry delivered late
  steadily keeps its real, old time) and a round trip longer than ``timesync.max_round_trip_s`` means no match;
  targets wait ``timesync.first_answer_wait_s`` for the first answer (``timesync.py``).
- The autopilot's own word: while its estimator status (EKF_STATUS_REPORT, ESTIMATOR_STATUS) says the attitude
  is not usable there is no match; while it says the horizontal position is not usable, states carry none.
- A gimbal (``gimbal.py``), when given, must report the camera's orientation at the capture time: else no match.

Attitude and position are interpolated between the two samples around the capture time, or taken from the
nearest one within ``window_s``, carried along its own rate (the gyro rates, the velocity) for at most
``max_extrapolation_s`` while that rate agrees with how the series moved; anything older is ignored rather
than guessed.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter
from typing import Dict, Optional, Tuple

import numpy as np

from edge_landing.runtime.core.camera import Attitude
from edge_landing.runtime.core.messages import TelemetryMatch, VehicleState
from edge_landing.runtime.io.clock_offset import ClockOffset
from edge_landing.runtime.io.gimbal import GimbalSeries
from edge_landing.runtime.io.position_resets import Emptied, FrameMoves, Quantity
from edge_landing.runtime.io.series import TimeSeries
from edge_landing.runtime.io.telemetry_config import TelemetryConfig

__all__ = ["ClockOffset", "TelemetryBuffer", "TelemetryConfig", "TelemetryMatch", "RANGEFINDER_DOWN"]
log = logging.getLogger(__name__)
RANGEFINDER_DOWN = 25  # MAV_SENSOR_ROTATION_PITCH_270
# Estimator flags, the same bits in ArduPilot's EKF_STATUS_REPORT and PX4's ESTIMATOR_STATUS.
ESTIMATOR_ATTITUDE, ESTIMATOR_POS_HORIZ_REL, ESTIMATOR_CONST_POS_MODE = 1, 8, 128


def _finite(*values: float) -> bool:
    return all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)


class TelemetryBuffer:
    """Thread-safe store of attitude, local position and height above ground, with counted rejections."""

    def __init__(self, config: TelemetryConfig = TelemetryConfig(), gimbal: Optional[GimbalSeries] = None):
        self.config, self.gimbal = config, gimbal
        self._lock = threading.Lock()
        self._attitude = TimeSeries(config.history_s, config.max_samples, config.max_extrapolation_s)
        self._position = TimeSeries(config.history_s, config.max_samples, config.max_extrapolation_s)
        self._range = TimeSeries(config.history_s, config.max_samples)
        self._rel_alt = TimeSeries(config.history_s, config.max_samples)
        self._clock = ClockOffset(config)
        self._rejected: Counter[str] = Counter()
        self._rates_refused: Counter[str] = Counter()          # samples whose rate matching does not use
        self.samples = 0
        self._position_epoch = 0
        self._estimator: Optional[Tuple[float, int, bool]] = None   # (arrival, flags, GPS glitch) of the newest
        self._moves = FrameMoves(config)                      # reboots, jumps and resets (position_resets.py)
        self._said_disagree = False

    def _all_series(self) -> Tuple[TimeSeries, ...]:
        return self._attitude, self._position, self._range, self._rel_alt

    # -- intake (link thread) ----------------------------------------------------------------------------
    def rejected(self) -> Dict[str, int]:
        """Rejected samples by reason (a copy), the gimbal's included."""
        with self._lock:
            out = dict(self._rejected)
        return out if self.gimbal is None else {**out, **self.gimbal.rejected()}

    def reject(self, reason: str) -> None:
        with self._lock:
            self._rejected[reason] += 1

    def local_time(self, remote_ms: Optional[float], arrival_s: Optional[float] = None) -> Optional[float]:
        """Map an autopilot ``time_boot_ms`` onto the local monotonic clock (None: dropped, and why in the clock's
        ``dropped_why``). Without a ``remote_ms`` (a caller that has no autopilot time) the arrival time is used;
        ``_add`` drops a message whose ``time_boot_ms`` is 0 or not a number before it gets here."""
        arrival_s = time.monotonic() if arrival_s is None else arrival_s
        if remote_ms is None:
            return arrival_s
        return self._clock.map(remote_ms / 1000.0, arrival_s)

    def stamp(self, remote_ms: float, arrival_s: float) -> Optional[float]:
        """``local_time`` for another message on the autopilot's clock (a gimbal report); None: not timed."""
        with self._lock:
            return self.local_time(remote_ms, arrival_s) if _finite(remote_ms) and remote_ms > 0 else None

    def _add(self, series: TimeSeries, value: np.ndarray, remote_ms: Optional[float], arrival_s: Optional[float],
             sample_s: Optional[float] = None, velocity: Optional[np.ndarray] = None,
             rate: Optional[np.ndarray] = None) -> bool:
        """``sample_s``: the sample's local time when the caller knows it (else mapped from ``remote_ms``);
        ``velocity``: a position sample's own NED velocity (m/s), when it carries one; ``rate``: the value's rate
        of change, kept for matching only while it agrees with the series (:meth:`_checked_rate`)."""
        arrival = time.monotonic() if arrival_s is None else arrival_s
        with self._lock:
            if sample_s is None and remote_ms is not None and not (_finite(remote_ms) and remote_ms > 0):
                # Stamped on its arrival instead, telemetry held back and delivered late would look fresh.
                self._rejected["sample without a time stamp (time_boot_ms 0): its age cannot be told"] += 1
                return False
            t = self.local_time(remote_ms, arrival) if sample_s is None else sample_s
            if t is None:
                self._rejected[self._clock.dropped_why] += 1
                return False
            remote_s = remote_ms / 1000.0 if sample_s is None and remote_ms is not None else None
            stale, why = self._frame_moved(series, t, value, velocity, remote_s)
            if stale:
                for old in stale:
                    old.clear()
                self._position_epoch += 1
                self._rejected[why] += 1
            rate = self._checked_rate(series, t, value, rate)
            if not series.add(t, value, arrival, rate):
                self._rejected["sample not newer than the last one (out of order, repeated or a frozen clock)"] += 1
                return False
            if series is self._position:
                self._moves.velocity.kept(t, velocity, remote_s)
            self.samples += 1
            return True

    def _checked_rate(self, series: TimeSeries, t_s: float, value: np.ndarray, rate: Optional[np.ndarray]
                      ) -> Optional[np.ndarray]:
        """``rate`` when it agrees with how the value changed since the newest sample (mean of both samples' rates
        against the difference quotient, within the tolerances of TelemetryConfig), else None. No sample before
        (or one more than twice the matching window before, or a position velocity the reset check distrusts):
        None, the sample is held as it is."""
        c = self.config
        angles = series is self._attitude
        if rate is None or (not angles and not self._moves.velocity.trusted):
            return None
        agrees = series.rate_agrees(t_s, value, rate, 2 * c.window_s,
                                    c.rate_tolerance_rad_s if angles else c.rate_tolerance_mps,
                                    c.rate_tolerance_share, angles)
        if agrees is None:
            return None
        if agrees:
            return rate
        name = "attitude rates" if angles else "position velocities"
        if name not in self._rates_refused:
            log.info("the autopilot's %s disagree with how its %s change: telemetry is held, not carried, to a "
                     "capture time past the newest sample", name, "angles" if angles else "positions")
        self._rates_refused[name] += 1
        return None

    def rates_refused(self) -> Dict[str, int]:
        """Samples whose rate was not used for matching (it disagreed with the series), by kind."""
        with self._lock:
            return dict(self._rates_refused)

    def _frame_moved(self, series: TimeSeries, t_s: float, value: np.ndarray, velocity: Optional[np.ndarray] = None,
                     remote_s: Optional[float] = None) -> Tuple[Tuple[TimeSeries, ...], str]:
        """The series to empty and the counted reason when this sample shows that the autopilot's frame moved
        since the newest sample of ``series`` (a reboot, a position or a heading faster than flight), else
        ((), "")."""
        kind = Quantity.POSITION if series is self._position else \
            Quantity.ATTITUDE if series is self._attitude else Quantity.OTHER
        last = (series.times[-1], series.values[-1]) if series.times else None
        emptied, why = self._moves.check(self._clock.reboots, kind, last, t_s, value, velocity, remote_s)
        if emptied is Emptied.ALL_SERIES:
            return self._all_series(), why
        return ((series,) if emptied is Emptied.THIS_SERIES else ()), why

    def add_attitude(self, roll_rad: float, pitch_rad: float, yaw_rad: float, remote_ms: Optional[float] = None,
                     arrival_s: Optional[float] = None, sample_s: Optional[float] = None,
                     body_rates_rad_s: Optional[Tuple[float, float, float]] = None) -> bool:
        """``body_rates_rad_s``: the gyro rates with the attitude (ATTITUDE's rollspeed, pitchspeed, yawspeed, body
        frame), used to carry the attitude to a capture time just past the newest sample (io.series)."""
        c = self.config
        if not _finite(roll_rad, pitch_rad, yaw_rad):
            self.reject("attitude not finite")
            return False
        if abs(roll_rad) > c.max_tilt_rad or abs(pitch_rad) > c.max_tilt_rad:
            self.reject("roll/pitch beyond the envelope")
            return False
        if abs(yaw_rad) > 2 * math.pi + 1e-3:
            self.reject("yaw out of range")
            return False
        rate = _euler_rates(roll_rad, pitch_rad, body_rates_rad_s, c.max_body_rate_rad_s)
        return self._add(self._attitude, np.array([roll_rad, pitch_rad, yaw_rad]), remote_ms, arrival_s, sample_s,
                         rate=rate)

    def add_position(self, north_m: float, east_m: float, down_m: float, remote_ms: Optional[float] = None,
                     arrival_s: Optional[float] = None, sample_s: Optional[float] = None,
                     velocity_ned_mps: Optional[Tuple[float, float, float]] = None) -> bool:
        """``velocity_ned_mps``: the autopilot's velocity with the position (LOCAL_POSITION_NED's vx, vy, vz), used
        to tell a reset from flight and to carry the position to a capture time just past the newest sample; a
        non-finite or implausible one is ignored."""
        if not _finite(north_m, east_m, down_m) or max(abs(north_m), abs(east_m), abs(down_m)) > self.config.max_position_m:
            self.reject("local position not finite or too far")
            return False
        velocity = None
        if velocity_ned_mps is not None and _finite(*velocity_ned_mps):
            v = np.array(velocity_ned_mps, dtype=np.float64)
            velocity = v if float(np.linalg.norm(v)) <= self.config.max_speed_mps else None
        return self._add(self._position, np.array([north_m, east_m, down_m]), remote_ms, arrival_s, sample_s, velocity,
                         rate=velocity)

    def add_relative_alt(self, alt_m: float, remote_ms: Optional[float] = None,
                         arrival_s: Optional[float] = None, sample_s: Optional[float] = None) -> bool:
        if not _finite(alt_m):
            self.reject("relative altitude not finite")
            return False
        if alt_m < 0:
            self.reject("negative height above ground")
            return False
        if alt_m > self.config.max_agl_m:
            self.reject("height above ground beyond its maximum")
            return False
        return self._add(self._rel_alt, np.array([alt_m]), remote_ms, arrival_s, sample_s)

    def add_rangefinder(self, distance_m: float, remote_ms: Optional[float] = None,
                        arrival_s: Optional[float] = None, min_m: float = 0.0, max_m: float = math.inf) -> bool:
        if not _finite(distance_m):
            self.reject("rangefinder not finite")
            return False
        if not min_m <= distance_m <= max_m or distance_m <= 0:
            self.reject("rangefinder outside its own range")
            return False
        return self._add(self._range, np.array([distance_m]), remote_ms, arrival_s)

    def add_estimator_status(self, flags: int, arrival_s: Optional[float] = None, glitch_flag: int = 0) -> None:
        """The autopilot's estimator status. While its newest one (within ``estimator_status_s``) says the
        attitude is not usable there is no telemetry; while it says the horizontal position is not usable
        (no relative position, constant-position mode, or ``glitch_flag``: a GPS glitch), frames get no position,
        so nothing is placed in or re-expressed from local NED (ARCHITECTURE.md §12)."""
        arrival = time.monotonic() if arrival_s is None else arrival_s
        with self._lock:
            self._estimator = (arrival, int(flags), bool(int(flags) & glitch_flag))
            bad = self._estimator_problem(arrival)
            if bad:
                self._rejected[f"the autopilot's estimator: {bad}"] += 1

    def _estimator_problem(self, now_s: float) -> str:
        """'' when the newest estimator status (if any, and recent) vouches for attitude and position."""
        if self._estimator is None or abs(now_s - self._estimator[0]) > self.config.estimator_status_s:
            return ""
        _, flags, glitch = self._estimator
        if not flags & ESTIMATOR_ATTITUDE:
            return "attitude not usable"
        if not flags & ESTIMATOR_POS_HORIZ_REL or flags & ESTIMATOR_CONST_POS_MODE or glitch:
            return "horizontal position not usable"
        return ""

    def add_state(self, state: VehicleState, local_time_s: float, arrival_s: Optional[float] = None) -> None:
        """A whole state sampled at a local time (a simulated camera's perfect telemetry), arrived at
        ``arrival_s`` (default: the sample time). Freshness counts from the arrival."""
        a, arrival = state.attitude, local_time_s if arrival_s is None else arrival_s
        self.add_attitude(a.roll_rad, a.pitch_rad, a.yaw_rad, arrival_s=arrival, sample_s=local_time_s)
        if state.position_ned_m is not None:
            n, e, d = (float(v) for v in state.position_ned_m)
            self.add_position(n, e, d, arrival_s=arrival, sample_s=local_time_s)
        if state.agl_m is not None:
            self.add_relative_alt(float(state.agl_m), arrival_s=arrival, sample_s=local_time_s)

    def forget(self) -> None:
        """Drop every sample (the autopilot changed or rebooted)."""
        with self._lock:
            for s in self._all_series():
                s.clear()
            self._clock.reset()
            self._moves.forget()
            self._position_epoch += 1

    def timesync_request(self, now_s: float) -> int:
        """The ``ts1`` (ns) of a TIMESYNC request about to be sent at ``now_s``."""
        with self._lock:
            return self._clock.round_trips.request(now_s)

    def timesync_reply(self, tc1_ns: int, ts1_ns: int, arrival_s: Optional[float] = None) -> bool:
        """The autopilot's answer to a request; False when it answers none of ours (another component's request
        on a shared link: ignored). An answer on another clock than the telemetry's is counted as rejected."""
        arrival = time.monotonic() if arrival_s is None else arrival_s
        with self._lock:
            trips = self._clock.round_trips
            if not trips.reply(int(tc1_ns), int(ts1_ns), arrival):
                return False
            offset, diff = self._clock.offset_s, self._clock.last_diff_s
            if offset is None or diff is None:
                return True
            trips.note_gap(self._clock.recent_delays())
            disagree = trips.agreement.why
            if disagree or trips.on_other_clock(arrival, diff):
                self._rejected["TIMESYNC answer on another clock than the telemetry's (ignored)"] += 1
                if disagree and not self._said_disagree:
                    self._said_disagree = True
                    log.warning("the autopilot's TIMESYNC answers are ignored from now on: %s (a real autopilot "
                                "stamps both with one clock); telemetry is timed by its own stamps only", disagree)
                return True
            bounds = trips.bounds_s(arrival, diff)
            late = self.config.window_s
            if bounds is not None and offset - bounds[1] > late and self._clock.delay_s <= late:
                # The samples kept so far were timed with an offset that took the link's delay for the clocks'
                # difference (the last one was not capped): older than placed, they would block re-timed ones.
                for series in self._all_series():
                    series.clear()
                self._rejected["samples timed before a TIMESYNC answer showed them late: dropped"] += 1
            return True

    def round_trips(self) -> Tuple[int, Optional[float]]:
        """(answers so far, the newest round trip in s or None)."""
        with self._lock:
            trips = self._clock.round_trips
            return trips.answered, trips.round_trip_s

    # -- queries (pipeline thread) -----------------------------------------------------------------------
    @property
    def reboots(self) -> int:
        """Times the autopilot's clock restarted (a reboot) since this buffer began."""
        with self._lock:
            return self._clock.reboots

    def last_arrival_s(self) -> float:
        """When the newest accepted attitude arrived (local monotonic seconds; -inf if never)."""
        with self._lock:
            return self._attitude.last_arrival_s

    def state_at(self, capture_time_s: float) -> Optional[VehicleState]:
        """The vehicle state at a capture time, or None when no attitude sample is close enough."""
        w = self.config.window_s
        with self._lock:
            att = self._attitude.at(capture_time_s, w, angles=True)
            pos = self._position.at(capture_time_s, w)
            rng = self._range.at(capture_time_s, w)
            rel = self._rel_alt.at(capture_time_s, w)
            epoch = self._position_epoch
            if self._estimator_problem(capture_time_s):   # attitude not usable is refused by ``lookup``
                pos = None
        if att is None:
            return None
        agl, source = _height_above_ground(rng, rel, att)
        attitude = Attitude(float(att[0]), float(att[1]), float(att[2]))
        mount = None if self.gimbal is None else self.gimbal.mount_at(capture_time_s, attitude)[0]
        return VehicleState(time_s=capture_time_s, attitude=attitude, agl_m=agl, agl_source=source,
                            position_ned_m=None if pos is None else pos.astype(np.float64), position_epoch=epoch,
                            camera_mount=mount)

    def newest_state(self) -> Optional[VehicleState]:
        """The vehicle state at the newest attitude sample's time (local clock), or None without one."""
        with self._lock:
            newest = self._attitude.times[-1] if self._attitude.times else None
        return None if newest is None else self.state_at(newest)

    def lookup(self, capture_time_s: float, now_s: Optional[float] = None) -> TelemetryMatch:
        """The state at a capture time with the freshness rule applied; ``reason`` says why it is not usable."""
        now_s = time.monotonic() if now_s is None else now_s
        last = self.last_arrival_s()
        if last == -math.inf:
            rejected = self.rejected()
            detail = f" ({sum(rejected.values())} rejected: {max(rejected, key=rejected.__getitem__)})" if rejected else ""
            return TelemetryMatch(None, "no telemetry" + detail)
        age = now_s - last
        if age > self.config.fresh_s:
            return TelemetryMatch(None, f"telemetry stale: last attitude {age:.2f} s ago")
        with self._lock:
            problem = self._estimator_problem(now_s)
            link = self._clock.round_trips.problem(now_s)
            delay_s = self._clock.delay_s
        if link:
            return TelemetryMatch(None, link)
        if problem.startswith("attitude"):
            return TelemetryMatch(None, f"the autopilot's estimator reports its {problem}")
        state = self.state_at(capture_time_s)
        if state is None:
            late = f" (TIMESYNC: telemetry arrives {delay_s:.1f} s after it was measured)" if delay_s > 0.1 else ""
            return TelemetryMatch(None, f"no telemetry within {self.config.window_s:g} s of the capture time{late}")
        gimbal_why = "" if self.gimbal is None else self.gimbal.why_not(capture_time_s, now_s)
        return TelemetryMatch(None, gimbal_why) if gimbal_why else TelemetryMatch(state)


def _euler_rates(roll_rad: float, pitch_rad: float, body_rates: Optional[Tuple[float, float, float]],
                 max_rate: float) -> Optional[np.ndarray]:
    """Euler angle rates (roll, pitch, yaw per second) from body rates p, q, r; None when not given, not finite or
    beyond ``max_rate`` (pitch is within the tilt envelope here, so cos(pitch) is far from 0)."""
    if body_rates is None or not _finite(*body_rates) or max(abs(float(v)) for v in body_rates) > max_rate:
        return None
    p, q, r = (float(v) for v in body_rates)
    sr, cr = math.sin(roll_rad), math.cos(roll_rad)
    cp, tp = math.cos(pitch_rad), math.tan(pitch_rad)
    return np.array([p + (q * sr + r * cr) * tp, q * cr - r * sr, (q * sr + r * cr) / cp])


def _height_above_ground(rng: Optional[np.ndarray], rel: Optional[np.ndarray],
                         att: np.ndarray) -> Tuple[Optional[float], str]:
    """A downward rangefinder measures along the body z axis: tilt it back to vertical."""
    if rng is not None and rng[0] > 0:
        tilt = math.cos(float(att[0])) * math.cos(float(att[1]))
        if tilt > 0.5:
            return float(rng[0]) * tilt, "rangefinder"
    if rel is not None and rel[0] >= 0:
        return float(rel[0]), "relative_alt"
    return None, ""
