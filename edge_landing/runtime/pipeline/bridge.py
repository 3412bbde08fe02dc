"""Keep ArduPilot's precision-landing estimator fed between frames that are slower than it needs (ARCHITECTURE.md §12).

ArduPilot needs LANDING_TARGET updates less than 0.5 s apart for 2 s before its estimator initialises, and a
gap in the stream fails the init ("PrecLand: Init Failed"). A pipeline that sends once per frame therefore
never lands precisely when a frame takes longer than that to arrive and be decided: a slow model (DenseDepth
runs at ~1 image/s on 2 cores), a loaded CPU, a camera that stalls for a moment, or the synthetic camera of
the closed loop (~3 frames/s).

The bridge re-sends the target the newest decided frame sent, re-expressed at the newest telemetry by the
caller (the same re-expression every held spot gets), when nothing has left for ``period_s``. It adds no
evidence and no spot: only a target a frame already decided to send, only until the next frame is decided
(a frame that sends nothing clears it at once), and it keeps that frame's capture time, so the link's age
limit (``LinkConfig.max_target_age_s``, what the autopilot accepts) ends it after a stall. Each re-send is
stamped (``time_usec``) with the time of the pose it is expressed at, not the capture time: ArduPilot takes a
message whose stamp repeats the last one's for a duplicate and feeds nothing with it. Pure state, no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

from edge_landing.runtime.core.messages import Target, VehicleState

DEFAULT_PERIOD_S = 0.2   # well inside ArduPilot's 0.5 s, with room for a loaded CPU's late wake-ups


@dataclass(frozen=True)
class Bridged:
    """What the newest decided frame sent, and the telemetry it was matched with (its position epoch)."""

    target: Target
    capture_state: Optional[VehicleState]


class TargetBridge:
    """Which target to re-send between frames, and when (times on the frames' clock, seconds)."""

    def __init__(self, period_s: float = DEFAULT_PERIOD_S):
        self.period_s = period_s
        self._last: Optional[Bridged] = None
        self._last_sent_s = float("-inf")
        self.resent = 0

    @property
    def enabled(self) -> bool:
        return self.period_s > 0

    def decided(self, target: Target, capture_state: Optional[VehicleState], sent: bool, now_s: float) -> None:
        """A frame's decision: a sent target with a local NED position (one that can be re-expressed at a newer
        pose) is kept for bridging; anything else clears what was kept."""
        if sent:
            self._last_sent_s = now_s
        keep = sent and self.enabled and target.valid and target.position_ned_m is not None
        self._last = Bridged(target, capture_state) if keep else None

    def due(self, now_s: float) -> Optional[Tuple[Target, Optional[VehicleState]]]:
        """The target to re-send now, with its frame's telemetry, or None (nothing kept, or sent recently)."""
        if self._last is None or now_s - self._last_sent_s < self.period_s:
            return None
        return self._last.target, self._last.capture_state

    def resent_at(self, now_s: float) -> None:
        self._last_sent_s = now_s
        self.resent += 1

    def clear(self) -> None:
        self._last = None
