"""When to ask the autopilot for each telemetry stream again (ARCHITECTURE.md §8). Pure logic; the link sends.

Every message edge-run reads is asked for with MAV_CMD_SET_MESSAGE_INTERVAL at the rate it needs. What is asked
that way does not last: ArduPilot and PX4 forget it when they reboot (they keep only their stored stream rates, which
may still send some messages, slower), and a ground station on the same link can set other rates. So a stream is
asked for again whenever it arrives at less than ``low_share`` of its rate over the last ``window_s``, not only when
every stream has stopped: after a reboot ATTITUDE at its stored 4 Hz would otherwise have hidden that
LOCAL_POSITION_NED never came back. A stream that stays slow (a radio that cannot carry more, a message the
autopilot does not send: DISTANCE_SENSOR without a rangefinder, the other autopilot's estimator status) is asked
again less and less often, ``first_retry_s`` doubling up to ``max_retry_s``; every stream is asked for at once after
a reboot, whatever its rate (the arrivals counted before it are forgotten), and a stream back at ``flowing_share``
of its rate starts the back-off over (a radio-limited stream hovering near ``low_share`` is not re-asked on every
crossing).
"""
from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import Deque, Dict, List, Tuple

__all__ = ["StreamRequestConfig", "StreamRequests"]
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StreamRequestConfig:
    """Seconds and shares of a stream's rate."""

    window_s: float = 2.0       # a stream's rate is counted over this long
    low_share: float = 0.5      # below this share of the rate asked for, it is asked for again
    flowing_share: float = 0.75  # at this share or more it flows: the back-off starts over
    first_retry_s: float = 3.0  # the first wait between two requests of a slow stream (then doubling) ...
    max_retry_s: float = 60.0   # ... up to this


class _Stream:
    def __init__(self, rate_hz: float, config: StreamRequestConfig):
        self.rate_hz = rate_hz
        self.arrivals: Deque[float] = deque(maxlen=max(8, int(math.ceil(2 * rate_hz * config.window_s))))
        self.next_ask_s = -math.inf
        self.retry_s = config.first_retry_s
        self.asked = 0
        self.was_flowing = False
        self.forced = False    # asked for on the next ``due`` whatever its rate (after a reboot)


class StreamRequests:
    """``wanted``: message name → the rate edge-run needs (Hz). ``arrived`` as each message of one comes in;
    ``due`` says which to ask for now, as (name, interval in µs)."""

    def __init__(self, wanted: Dict[str, float], config: StreamRequestConfig = StreamRequestConfig()):
        self.config = config
        self._streams = {name: _Stream(rate, config) for name, rate in wanted.items()}
        self._reboots = 0

    def arrived(self, name: str, now_s: float) -> None:
        stream = self._streams.get(name)
        if stream is not None:
            stream.arrivals.append(now_s)

    def rate_hz(self, name: str, now_s: float) -> float:
        """How often ``name`` arrived over the last ``window_s``."""
        stream = self._streams[name]
        window = self.config.window_s
        return sum(1 for t in stream.arrivals if now_s - window < t <= now_s) / window

    def due(self, now_s: float, reboots: int = 0) -> List[Tuple[str, float]]:
        """The streams to ask for now. ``reboots``: how often the autopilot has rebooted so far (a new count asks
        for every stream at once)."""
        if reboots != self._reboots:
            self._reboots = reboots
            log.info("the autopilot rebooted: its telemetry streams are asked for again")
            for stream in self._streams.values():
                stream.next_ask_s, stream.retry_s, stream.was_flowing = -math.inf, self.config.first_retry_s, False
                stream.arrivals.clear()
                stream.forced = True
        out = []
        for name, stream in self._streams.items():
            rate = self.rate_hz(name, now_s)
            if rate >= self.config.flowing_share * stream.rate_hz:
                stream.retry_s, stream.was_flowing = self.config.first_retry_s, True
                stream.next_ask_s = min(stream.next_ask_s, now_s)
            if not stream.forced and (rate >= self.config.low_share * stream.rate_hz or now_s < stream.next_ask_s):
                continue
            stream.forced = False
            if stream.was_flowing:
                log.info("%s arrives at %.1f/s, %.0f/s asked for: asked for again", name, rate, stream.rate_hz)
                stream.was_flowing = False
            stream.next_ask_s = now_s + stream.retry_s
            stream.retry_s = min(2.0 * stream.retry_s, self.config.max_retry_s)
            stream.asked += 1
            out.append((name, 1e6 / stream.rate_hz))
        return out

    def asked(self, name: str) -> int:
        """Times ``name`` has been asked for."""
        return self._streams[name].asked
