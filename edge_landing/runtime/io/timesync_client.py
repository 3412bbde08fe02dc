"""The link's side of TIMESYNC (``timesync.py`` holds the clock arithmetic): requests to the autopilot, its answers,
and answers to its own requests. Runs in the link's thread only (``mavlink_link.py``)."""
from __future__ import annotations

import logging
import math
import time
from typing import Any, Callable

from edge_landing.runtime.io.link_config import LinkCounts
from edge_landing.runtime.io.telemetry import TelemetryBuffer

__all__ = ["TimesyncClient"]
log = logging.getLogger(__name__)


class TimesyncClient:
    """A request every ``timesync.period_s`` once the autopilot is known; answers go to the telemetry buffer."""

    def __init__(self, telemetry: TelemetryBuffer, counts: LinkCounts, send: Callable[[Any], bool], mavlink: Any):
        self.telemetry, self.counts, self._send, self._m = telemetry, counts, send, mavlink
        self._next_s = 0.0
        self._said = False
        self._last_answer_s = -math.inf

    def tick(self, now: float) -> None:
        """A TIMESYNC request to the autopilot when due: its answers tell how late telemetry arrives. Said once
        whether it answers: without answers a steady delay looks like a clock offset."""
        period = self.telemetry.config.timesync.period_s
        if now < self._next_s:
            return
        self._next_s = now + period
        answered, round_trip = self.telemetry.round_trips()
        if not self._said and (answered or self.counts["timesync_requests"] * period >= 3.0):
            self._said = True
            if answered:
                log.info("the autopilot answers TIMESYNC (round trip %.0f ms): telemetry that arrives late is "
                         "refused by its real age", 1000.0 * (round_trip or 0.0))
            else:
                log.warning("the autopilot does not answer TIMESYNC: telemetry delayed steadily on the link cannot "
                            "be told from a clock offset (one-way time stamps only)")
        ts1 = self.telemetry.timesync_request(time.monotonic())
        if self._send(self._m.MAVLink_timesync_message(0, ts1)):
            self.counts.add("timesync_requests")

    def on_message(self, msg: Any, arrival: float) -> None:
        """An answer to our request, or the autopilot's own request (answered with this clock, in ns, as a
        MAVLink component should: PX4 converts our LANDING_TARGET time stamps with it)."""
        if int(msg.tc1) != 0:
            if self.telemetry.timesync_reply(int(msg.tc1), int(msg.ts1), arrival):
                self.counts.add("timesync_answers")
            return
        if arrival - self._last_answer_s >= 0.05:      # a flood of requests gets at most 20 answers a second
            self._last_answer_s = arrival
            self._send(self._m.MAVLink_timesync_message(int(arrival * 1e9), int(msg.ts1)))
