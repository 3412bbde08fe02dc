"""Telemetry samples matched to a frame's capture time (ARCHITECTURE.md §3: capture time, not inference end).

The link thread calls ``add_*`` as messages arrive; the pipeline asks ``state_at(capture_time_s)``.
Autopilot timestamps (``time_boot_ms``) are mapped onto this computer's monotonic clock with the smallest
observed (arrival - sent) offset, i.e. the sample that travelled fastest, so transport jitter does not smear
the match. Attitude and position are interpolated between the two samples around the capture time, or taken
from the nearest one within ``window_s``; anything older is ignored rather than guessed.
"""
from __future__ import annotations

import bisect
import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Deque, Optional, Tuple

import numpy as np

from edge_landing.runtime.core.camera import Attitude
from edge_landing.runtime.core.messages import VehicleState

RANGEFINDER_DOWN = 25  # MAV_SENSOR_ROTATION_PITCH_270


@dataclass(frozen=True)
class TelemetryConfig:
    window_s: float = 0.25      # how far from the capture time a sample may be and still count
    history_s: float = 5.0      # how much history to keep
    reboot_jump_s: float = 2.0  # a remote clock that goes back this much means the autopilot rebooted


class _Series:
    """Time-sorted samples of one quantity (times on the local monotonic clock)."""

    def __init__(self, history_s: float):
        self.history_s = history_s
        self.times: Deque[float] = deque()
        self.values: Deque[np.ndarray] = deque()

    def add(self, t_s: float, value: np.ndarray) -> None:
        if self.times and t_s < self.times[-1]:
            return  # out-of-order sample (e.g. duplicated stream): keep the series sorted
        self.times.append(t_s)
        self.values.append(value)
        while self.times and self.times[0] < t_s - self.history_s:
            self.times.popleft()
            self.values.popleft()

    def at(self, t_s: float, window_s: float, angles: bool = False) -> Optional[np.ndarray]:
        if not self.times:
            return None
        times = list(self.times)
        i = bisect.bisect_left(times, t_s)
        before = i - 1 if i > 0 else None
        after = i if i < len(times) else None
        if before is not None and after is not None and times[after] - times[before] <= 2 * window_s:
            t0, t1 = times[before], times[after]
            v0, v1 = self.values[before], self.values[after]
            w = 0.0 if t1 == t0 else (t_s - t0) / (t1 - t0)
            delta = v1 - v0
            if angles:  # interpolate the short way round (yaw wraps at ±pi)
                delta = (delta + math.pi) % (2 * math.pi) - math.pi
            return v0 + w * delta
        best = min((j for j in (before, after) if j is not None), key=lambda j: abs(times[j] - t_s))
        return self.values[best] if abs(times[best] - t_s) <= window_s else None


class TelemetryBuffer:
    """Thread-safe store of attitude, local position and height above ground."""

    def __init__(self, config: TelemetryConfig = TelemetryConfig()):
        self.config = config
        self._lock = threading.Lock()
        self._attitude = _Series(config.history_s)
        self._position = _Series(config.history_s)
        self._range = _Series(config.history_s)
        self._rel_alt = _Series(config.history_s)
        self._offset_s: Optional[float] = None
        self._last_remote_s = -math.inf
        self.samples = 0

    def local_time(self, remote_ms: Optional[float], arrival_s: Optional[float] = None) -> float:
        """Map an autopilot ``time_boot_ms`` onto the local monotonic clock."""
        arrival_s = time.monotonic() if arrival_s is None else arrival_s
        if remote_ms is None or remote_ms <= 0:
            return arrival_s
        remote_s = remote_ms / 1000.0
        if remote_s < self._last_remote_s - self.config.reboot_jump_s:
            self._offset_s = None  # the autopilot rebooted: its clock restarted
        self._last_remote_s = remote_s
        offset = arrival_s - remote_s
        if self._offset_s is None or offset < self._offset_s:
            self._offset_s = offset
        return remote_s + self._offset_s

    def add_attitude(self, roll_rad: float, pitch_rad: float, yaw_rad: float, remote_ms: Optional[float] = None,
                     arrival_s: Optional[float] = None) -> None:
        with self._lock:
            self._attitude.add(self.local_time(remote_ms, arrival_s), np.array([roll_rad, pitch_rad, yaw_rad]))
            self.samples += 1

    def add_position(self, north_m: float, east_m: float, down_m: float, remote_ms: Optional[float] = None,
                     arrival_s: Optional[float] = None) -> None:
        with self._lock:
            self._position.add(self.local_time(remote_ms, arrival_s), np.array([north_m, east_m, down_m]))
            self.samples += 1

    def add_relative_alt(self, alt_m: float, remote_ms: Optional[float] = None,
                         arrival_s: Optional[float] = None) -> None:
        with self._lock:
            self._rel_alt.add(self.local_time(remote_ms, arrival_s), np.array([alt_m]))
            self.samples += 1

    def add_rangefinder(self, distance_m: float, remote_ms: Optional[float] = None,
                        arrival_s: Optional[float] = None) -> None:
        with self._lock:
            self._range.add(self.local_time(remote_ms, arrival_s), np.array([distance_m]))
            self.samples += 1

    def add_state(self, state: VehicleState, local_time_s: float) -> None:
        """A whole state known at a local time (a simulated camera's perfect telemetry)."""
        a = state.attitude
        self.add_attitude(a.roll_rad, a.pitch_rad, a.yaw_rad, arrival_s=local_time_s)
        if state.position_ned_m is not None:
            self.add_position(*(float(v) for v in state.position_ned_m), arrival_s=local_time_s)
        if state.agl_m is not None:
            self.add_relative_alt(float(state.agl_m), arrival_s=local_time_s)

    def state_at(self, capture_time_s: float) -> Optional[VehicleState]:
        """The vehicle state at a capture time, or None when no attitude sample is close enough."""
        w = self.config.window_s
        with self._lock:
            att = self._attitude.at(capture_time_s, w, angles=True)
            pos = self._position.at(capture_time_s, w)
            rng = self._range.at(capture_time_s, w)
            rel = self._rel_alt.at(capture_time_s, w)
        if att is None:
            return None
        agl, source = _height_above_ground(rng, rel, att)
        return VehicleState(time_s=capture_time_s, attitude=Attitude(float(att[0]), float(att[1]), float(att[2])),
                            position_ned_m=None if pos is None else pos.astype(np.float64),
                            agl_m=agl, agl_source=source)


def _height_above_ground(rng: Optional[np.ndarray], rel: Optional[np.ndarray],
                         att: np.ndarray) -> Tuple[Optional[float], str]:
    """A downward rangefinder measures along the body z axis: tilt it back to vertical."""
    if rng is not None and rng[0] > 0:
        tilt = math.cos(float(att[0])) * math.cos(float(att[1]))
        if tilt > 0.5:
            return float(rng[0]) * tilt, "rangefinder"
    if rel is not None:
        return float(rel[0]), "relative_alt"
    return None, ""
