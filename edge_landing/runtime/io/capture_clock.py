"""When a camera device's image was taken: the driver's buffer time stamp, when it is on this clock.

Telemetry is matched to a frame's capture time (ARCHITECTURE.md §3). A frame stamped when ``read()`` returns
is late by the camera's own latency (exposure, USB transfer, decoding: tens of milliseconds), and the attitude
matched to it then describes the drone that much later: at 30°/s of yaw, 50 ms is 1.5°, which moves a ground
point 1.3 m at 50 m range.

OpenCV's V4L2 backend reports the time stamp of the buffer it dequeued as ``CAP_PROP_POS_MSEC``. Linux
drivers stamp buffers with CLOCK_MONOTONIC (``V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC``, the usual case, uvcvideo
included), the clock of Python's ``time.monotonic()``; a few stamp with another clock, or not at all (0).
A stamp is used only where it is plausible on this clock: not in the future, at most ``max_age_s`` old when
read, and later than the previous frame's capture time. Otherwise the frame is stamped on arrival less the
latency the last plausible stamp showed (none before one), so capture times keep their order (motion geometry
drops its evidence when time goes back); a frame that even so would not come after the previous one is marked
invalid. The log says once that the driver's stamps are used, and once that one was not, and why.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Set, Tuple

log = logging.getLogger(__name__)

__all__ = ["DriverClockConfig", "DriverClock"]


@dataclass(frozen=True)
class DriverClockConfig:
    # A stamp older than this when the image is read is on another clock (or the driver held the buffer that
    # long, and then it is no capture time worth trusting either).
    max_age_s: float = 0.5
    # Stamps taken in the kernel just before time.monotonic() is read here may not be later; allow rounding
    # (OpenCV reports whole microseconds).
    future_tolerance_s: float = 0.002


class DriverClock:
    """Turns the driver's time stamp of each image into a capture time on the monotonic clock."""

    def __init__(self, name: str, config: DriverClockConfig = DriverClockConfig()):
        self.name = name
        self.config = config
        self.used = 0           # images stamped with the driver's time
        self.on_arrival = 0     # images stamped on arrival (no usable driver stamp)
        self._last_s = -math.inf
        self.latency_s = 0.0    # how old the last usable stamp was when read
        self._said: Set[str] = set()

    def capture_time_s(self, driver_ms: float, now_s: float) -> Tuple[float, str]:
        """(capture time on the monotonic clock, problem) for a driver stamp in ms read at ``now_s``; the problem
        is '' unless the frame cannot be placed after the previous one (then it is to be marked invalid)."""
        t_s = float(driver_ms) / 1000.0 if math.isfinite(driver_ms) else math.nan
        why = self._why_not(t_s, now_s)
        if not why:
            self._last_s, self.latency_s = t_s, now_s - t_s
            self.used += 1
            self._say("driver", f"camera {self.name}: frames stamped with the driver's capture time (the first was "
                                f"{1000.0 * self.latency_s:.0f} ms old when read)")
            return t_s, ""
        self.on_arrival += 1
        self._say("on_arrival", f"camera {self.name}: a frame stamped on arrival" + (
            f" less the latency earlier frames showed ({1000.0 * self.latency_s:.0f} ms)" if self.used else "")
            + f": {why}")
        estimate = now_s - self.latency_s
        if estimate <= self._last_s:
            return self._last_s, f"camera time stamp not usable ({why}) and no later than the previous frame's"
        self._last_s = estimate
        return estimate, ""

    def _why_not(self, t_s: float, now_s: float) -> str:
        c = self.config
        if not t_s > 0:
            return "the driver gives no time stamp"
        age = now_s - t_s
        if age < -c.future_tolerance_s:
            return f"the driver's stamp is {-age:.3f} s in the future of this clock"
        if age > c.max_age_s:
            return f"the driver's stamp is {age:.3f} s old when read (another clock, or a stalled buffer)"
        if t_s <= self._last_s:
            return "the driver's stamp is not later than the previous frame's capture time"
        return ""

    def _say(self, mode: str, line: str) -> None:
        if mode not in self._said:
            self._said.add(mode)
            (log.info if mode == "driver" else log.warning)(line)
