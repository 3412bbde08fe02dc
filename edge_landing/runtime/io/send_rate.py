"""A cap on how often one kind of message leaves: the camera, not the autopilot, sets edge-run's frame rate.

A video file is read as fast as the CPU allows (hundreds of frames/s for a small one) and a fast camera gives
60+; each frame's target would leave at that rate. ArduPilot uses the newest LANDING_TARGET only (its estimator
needs one at least every 0.5 s), and a telemetry radio at 57600 baud carries about 5.7 kB/s in all: at 20 Hz
the targets take a quarter of it. Pure state, no I/O.
"""
from __future__ import annotations

from typing import Optional

from edge_landing.runtime.core.errors import InputError


def check_cap_hz(hz: float, name: str) -> None:
    """Refuse a cap ArduPilot cannot live with: 0 (no cap) or 2-1000 Hz (its estimator needs a target at least
    every 0.5 s). ``name`` says where the value came from (a flag, a setting)."""
    if not (hz == 0 or 2.0 <= hz <= 1000.0):
        raise InputError(f"{name} must be 0 (no cap) or 2-1000 Hz: ArduPilot needs a target at least every 0.5 s, "
                         f"got {hz}")


class SendRate:
    """At most ``max_hz`` messages per second on average (0: no cap), the newest offered at each chance.

    Credit accrues with time and is spent per message; up to two messages' worth is kept, so a camera a little
    faster than the cap (25 frames/s under 20 Hz) still sends at the cap on average instead of every other frame.
    Times are seconds on one monotonic clock."""

    def __init__(self, max_hz: float):
        self.period_s = 1.0 / max_hz if max_hz > 0 else 0.0
        self._credit = 1.0
        self._last_s: Optional[float] = None

    def allow(self, now_s: float) -> bool:
        """Whether a message may leave now (and, if so, spend its credit)."""
        if self.period_s == 0.0:
            return True
        if self._last_s is not None:
            self._credit = min(2.0, self._credit + max(0.0, now_s - self._last_s) / self.period_s)
        self._last_s = now_s
        if self._credit >= 1.0:
            self._credit -= 1.0
            return True
        return False
