"""The autopilot-to-companion clock offset (ARCHITECTURE.md §12, "Clock offset on a sliding window").

A windowed jitter correction like ArduPilot's (GCS_Common.cpp, JitterCorrection): the offset follows the fastest
sample at once, and is re-estimated from the fastest sample of every window, so a drifting autopilot clock never
loses telemetry for good; a re-estimate raises it by no more than the clocks can drift apart (``max_drift``).
Unlike ArduPilot's, a sample more than 500 ms late is not moved forward, nor the offset with it: a late sample
keeps its own time, so telemetry held back and delivered in a burst is not matched to frames captured after it
was measured. A sample stamped from the future by more than ``max_future_s`` is dropped, and so is one stamped
``reboot_jump_s`` before the last until the clock has stayed behind for a window (then the autopilot rebooted).
When the autopilot answers TIMESYNC, samples are mapped with the offset kept within what its round trips allow
(``timesync.py``): a link that delays all telemetry steadily does not pass the delay off as an offset, and a
clock that runs slower than ``max_drift`` lets (a lagging simulator) is followed.
"""
from __future__ import annotations

import math
from collections import deque
from typing import TYPE_CHECKING, Deque, Optional

from edge_landing.runtime.io.timesync import RoundTrips

if TYPE_CHECKING:
    from edge_landing.runtime.io.telemetry_config import TelemetryConfig


class ClockOffset:
    """Autopilot-to-companion clock offset, re-estimated over a sliding window (never a minimum kept forever)."""

    def __init__(self, config: TelemetryConfig):
        self.config = config
        self.offset_s: Optional[float] = None
        self._window_start_s = 0.0
        self._window_min_s = math.inf
        self._recent: Deque[tuple[float, float]] = deque(maxlen=1024)   # (arrival, delay), two TIMESYNC periods
        self._last_remote_s = -math.inf
        self._future_since_s: Optional[float] = None
        self._behind_since_s: Optional[float] = None
        # The fastest sample of each of the last few windows: what the link has recently shown it can do. A
        # sample "from the future" is judged against these, not against the offset alone, which a starved
        # window (the receiving thread held up) can have raised: the next fast sample must then bring it back.
        self._recent_minima: Deque[float] = deque(maxlen=config.clock_memory_windows)
        self.dropped_why = ""         # why the last sample mapped to None was dropped
        self.reboots = 0              # times the remote clock restarted (an autopilot reboot)
        self.round_trips = RoundTrips(config.timesync, config.max_drift)
        self.delay_s = 0.0            # how much earlier the round trips put the last sample than the offset did
        self.last_diff_s: Optional[float] = None   # the last sample's arrival minus its stamp

    def recent_delays(self) -> list[tuple[float, float]]:
        """(arrival, arrival minus stamp) of the samples of the last two TIMESYNC periods."""
        return list(self._recent)

    def reset(self) -> None:
        self.offset_s, self._future_since_s, self._behind_since_s = None, None, None
        self._recent_minima.clear()
        self._recent.clear()
        self.round_trips.forget_clock()

    def _restarted(self, remote_s: float, arrival_s: float) -> bool:
        """Stamped ``reboot_jump_s`` before the last sample (the clock went back) or, once it has, still that far
        behind the clock followed so far (a restarted clock soon passes the last time stamp of a short-lived one)."""
        if remote_s < self._last_remote_s - self.config.reboot_jump_s:
            return True
        return (self._behind_since_s is not None and self.offset_s is not None
                and arrival_s - remote_s > self.offset_s + self.config.reboot_jump_s)

    def map(self, remote_s: float, arrival_s: float) -> Optional[float]:
        """Local time of a remote timestamp, or None for a sample from the future (dropped)."""
        c = self.config
        if self._restarted(remote_s, arrival_s):
            # Stamped well before the last sample: a reboot, or old samples replayed (a router's buffer, a log).
            # Only a clock that stays behind for a whole window has restarted; until then its samples are dropped.
            # Restarting on the first one let a single replayed sample be mapped onto its arrival, as fresh.
            if self._behind_since_s is None:
                self._behind_since_s = arrival_s
            if arrival_s - self._behind_since_s < c.clock_window_s:
                self.dropped_why = "sample stamped seconds before the last one (replayed, or a reboot not yet confirmed)"
                return None
            self.reset()  # the autopilot rebooted: its clock restarted
            self.reboots += 1
        self._behind_since_s = None
        diff = arrival_s - remote_s
        if self.offset_s is None:
            self.offset_s, self._window_start_s, self._window_min_s = diff, arrival_s, diff
        elif diff < min([self.offset_s, *self._recent_minima]) - c.max_future_s:
            # Stamped from the future: one glitch is dropped; a clock that stays ahead for a whole window
            # has jumped, and is re-learnt from there.
            if self._future_since_s is None:
                self._future_since_s = arrival_s
            if arrival_s - self._future_since_s < c.clock_window_s:
                self.dropped_why = "sample stamped from the future"
                return None
            self.offset_s, self._window_start_s, self._window_min_s = diff, arrival_s, diff
        self._future_since_s = None
        self._last_remote_s = remote_s
        self.offset_s = min(self.offset_s, diff)           # a faster sample: adopt at once
        self._window_min_s = min(self._window_min_s, diff)
        self._recent.append((arrival_s, diff))
        while self._recent and arrival_s - self._recent[0][0] > 2 * c.timesync.period_s:
            self._recent.popleft()
        elapsed_s = arrival_s - self._window_start_s
        if elapsed_s >= c.clock_window_s:
            # Forget older minima, so a drifting clock is followed; but only as fast as clocks drift: a window
            # whose fastest sample is much later than the offset shows a delayed link, not a slower clock.
            self.offset_s = min(self._window_min_s, self.offset_s + c.max_drift * elapsed_s)
            self._recent_minima.append(self._window_min_s)
            self._window_start_s, self._window_min_s = arrival_s, diff
        self.last_diff_s = diff
        # Kept within what the round trips allow: the windowed offset takes a steady delay for the clocks'
        # difference (too high) and lags behind a clock that runs slow (too low). Never above this sample's delay.
        bounds = self.round_trips.bounds_s(arrival_s, diff)
        if bounds is None:
            self.delay_s = 0.0
            return remote_s + self.offset_s
        used = min(max(self.offset_s, bounds[0]), bounds[1], diff)
        self.delay_s = max(self.offset_s - used, 0.0)
        return remote_s + used
