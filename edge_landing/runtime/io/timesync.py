"""Round trips to the autopilot (MAVLink TIMESYNC): how late its telemetry arrives, whatever its time stamps say.

One-way time stamps cannot tell a link that delivers everything D seconds late from an autopilot clock D seconds
behind this one: the clock offset (``clock_offset.py``) takes the fastest sample's delay for the offset, so
telemetry delayed steadily from the start, or for longer than the offset's drift allowance, looks fresh. A
TIMESYNC request answered with the autopilot's boot clock (ArduPilot: ``tc1`` = the time it received the
request, in ns, ``ts1`` echoed; PX4 likewise) bounds the offset from both sides, with no assumption about the
link: ``sent - tc1 <= offset <= arrival - tc1``. Telemetry is mapped with an offset kept within those bounds:
the upper one makes telemetry that arrives late steadily keep its real, old time; the lower one keeps a clock that
runs slower than the windowed offset can follow (a lagging simulator) from making on-time telemetry look old. A
round trip longer than ``max_round_trip_s`` means the link cannot deliver in time at all. Answers whose clock is
not the telemetry's (``ClockAgreement``) are ignored.

Pure bookkeeping on the local monotonic clock: the link thread calls ``request`` and ``reply``, the telemetry
buffer ``note_gap``, ``bounds_s`` and ``problem``; all under the buffer's lock. Memory is bounded (``max_pending``,
``anchors``, the agreement's 64 gaps).
"""
from __future__ import annotations

import math
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Deque, Iterable, Optional, Tuple

__all__ = ["Anchor", "ClockAgreement", "RoundTrips", "TimeSyncConfig"]


@dataclass(frozen=True)
class TimeSyncConfig:
    """Seconds, on the local monotonic clock."""

    # Four requests a second (ArduPilot and PX4 answer every one; 28 bytes each way): between answers a slow clock's
    # lower bound lags, so their spacing × how slow it runs must stay within the match window.
    period_s: float = 0.25
    # A link whose round trip is longer than this cannot deliver telemetry, nor a target, within the ~1 s the
    # autopilot accepts (LinkConfig.max_target_age_s): no telemetry is trusted until a round trip is short again.
    max_round_trip_s: float = 1.0
    # Targets wait this long after the first request for the first answer, so that a link delayed from the start
    # sends nothing before it is measured; an autopilot that never answers is trusted as before (one-way stamps).
    first_answer_wait_s: float = 1.0
    pending_s: float = 30.0         # an answer to a request older than this is not matched (a slow answer is)
    max_pending: int = 64
    anchors: int = 32               # the offset bounds kept (8 s of answers: rate_span_s fits)
    # An answer that puts the autopilot's clock further from its telemetry's than this is on another clock (an
    # autopilot whose TIMESYNC is not its boot clock) and is ignored; closer, it is a delay, and telemetry is late.
    max_delay_s: float = 30.0
    tolerance_s: float = 0.05       # time_boot_ms counts whole milliseconds; tc1 is in ns
    # The autopilot's clock rate is read from two answers at least this far apart: its error is the two round
    # trips over the span, so a long span keeps a slow link from passing for a slow clock.
    rate_span_s: float = 2.0
    # The gap between the telemetry's clock and the answers' (ClockAgreement): drifting faster than
    # ``max_gap_drift`` (s/s) over four ``drift_bin_s`` bins, or jumping ``max_gap_jump_s`` across a reboot, it is
    # another clock, and the answers are ignored.
    max_gap_drift: float = 0.01
    drift_bin_s: float = 1.0
    max_gap_jump_s: float = 1.0


@dataclass(frozen=True)
class Anchor:
    """One answered request: the offset (local - remote clock, s) was within [low_s, high_s] at ``at_s``."""

    low_s: float
    high_s: float
    at_s: float


class ClockAgreement:
    """Whether the answers' clock is the telemetry's (ArduPilot's and PX4's are: both are the boot clock).

    The gap between them (the fastest recent sample's delay minus the answers' offset) is steady for one clock,
    whatever the link; it steps when a delay starts or ends. It drifts steadily, at the same rate second after
    second, only when the two are different clocks, and it jumps at a reboot when the answers' clock did not
    restart with the telemetry's (a test double's, a router's). Then the answers are ignored from then on."""

    def __init__(self, config: TimeSyncConfig):
        self.config = config
        self._gaps: Deque[Tuple[float, float, int]] = deque(maxlen=64)   # (local time, gap s, epoch)
        self._epoch = 0
        self.why = ""

    def new_epoch(self) -> None:
        self._epoch += 1

    def add(self, at_s: float, gap_s: float) -> None:
        c = self.config
        if self.why:
            return
        if self._gaps and self._gaps[-1][2] != self._epoch and abs(gap_s - self._gaps[-1][1]) > c.max_gap_jump_s:
            self.why = (f"its TIMESYNC clock did not restart with its telemetry's at a reboot (moved "
                        f"{gap_s - self._gaps[-1][1]:+.1f} s against it)")
        self._gaps.append((at_s, gap_s, self._epoch))
        self._judge_drift(at_s)

    def _judge_drift(self, now_s: float) -> None:
        """Four consecutive ``drift_bin_s`` bins whose mean gaps all move the same way by similar amounts: a drift,
        not a step (a delay that starts moves one or two bins' means, not three differences)."""
        c = self.config
        bins: list[list[float]] = [[], [], [], []]
        for t, g, e in self._gaps:
            k = int((now_s - t) // c.drift_bin_s)
            if e == self._epoch and 0 <= k < 4:
                bins[3 - k].append(g)
        if any(len(b) < 2 for b in bins):
            return
        means = [sum(b) / len(b) for b in bins]
        steps = [b - a for a, b in zip(means, means[1:])]
        least, most = min(abs(d) for d in steps), max(abs(d) for d in steps)
        same_way = all(d > 0 for d in steps) or all(d < 0 for d in steps)
        if same_way and least > c.max_gap_drift * c.drift_bin_s and most <= 3.0 * least:
            rate = sum(steps) / (3.0 * c.drift_bin_s)
            self.why = f"its TIMESYNC clock and its telemetry's drift {100 * rate:+.1f} % apart"


class RoundTrips:
    """Pending TIMESYNC requests, the offset bounds their answers gave, and the newest round trip."""

    def __init__(self, config: TimeSyncConfig = TimeSyncConfig(), max_drift: float = 0.1):
        self.config = config
        self.max_drift = max_drift      # how fast the clocks may drift apart without answers that show more
        self._pending: OrderedDict[int, float] = OrderedDict()   # ts1 (ns) -> sent (local s)
        self._anchors: Deque[Anchor] = deque(maxlen=config.anchors)
        self._last_ts1 = 0
        self.first_request_s: Optional[float] = None
        self.round_trip_s: Optional[float] = None   # the newest answer's
        self.answered = 0
        self.agreement = ClockAgreement(config)

    def request(self, now_s: float) -> int:
        """A new request's ``ts1`` (ns, unique and increasing), remembered with its send time."""
        ts1 = max(int(now_s * 1e9), self._last_ts1 + 1)
        self._last_ts1 = ts1
        self._pending[ts1] = now_s
        while self._pending and (len(self._pending) > self.config.max_pending
                                 or now_s - next(iter(self._pending.values())) > self.config.pending_s):
            self._pending.popitem(last=False)
        if self.first_request_s is None:
            self.first_request_s = now_s
        return ts1

    def reply(self, tc1_ns: int, ts1_ns: int, arrival_s: float) -> bool:
        """An answer (``tc1`` the autopilot's clock, ns); False when it answers no request of ours."""
        sent_s = self._pending.pop(int(ts1_ns), None)
        if sent_s is None or not tc1_ns > 0 or arrival_s < sent_s:
            return False
        remote_s = tc1_ns / 1e9
        self._anchors.append(Anchor(sent_s - remote_s, arrival_s - remote_s, arrival_s))
        self.round_trip_s = arrival_s - sent_s
        self.answered += 1
        return True

    def forget_clock(self) -> None:
        """The autopilot rebooted: its clock restarted, so earlier bounds mean nothing."""
        self._anchors.clear()
        self.agreement.new_epoch()

    def note_gap(self, samples: Iterable[Tuple[float, float]]) -> None:
        """Samples' (arrival, delay = arrival minus stamp, s): the fastest of those that arrived between the two
        newest answers, against the answers' offset interpolated to its arrival, is the clocks' gap then."""
        if len(self._anchors) < 2:
            return
        a, b = self._anchors[-2], self._anchors[-1]
        if b.at_s <= a.at_s:
            return
        m0, m1 = 0.5 * (a.low_s + a.high_s), 0.5 * (b.low_s + b.high_s)
        gaps = [d - (m0 + (m1 - m0) * (t - a.at_s) / (b.at_s - a.at_s)) for t, d in samples if a.at_s < t <= b.at_s]
        if gaps:
            self.agreement.add(b.at_s, min(gaps))

    def drift_bounds(self) -> Tuple[float, float]:
        """How fast the offset may shrink and grow (s/s, the first <= -``max_drift``, the second >= ``max_drift``):
        as fast as two answers ``rate_span_s`` apart or more allow, beyond ``max_drift``: a simulator lagging behind
        real time (its clock, and its telemetry's, runs slow: the offset grows, at most 1 s/s) or sped up (it
        shrinks, at most 10 s/s)."""
        d = self.max_drift
        if len(self._anchors) < 2:
            return -d, d
        new = self._anchors[-1]
        old = next((a for a in self._anchors if new.at_s - a.at_s >= self.config.rate_span_s), None)
        if old is None:
            return -d, d
        span = new.at_s - old.at_s
        slowest, fastest = (new.low_s - old.high_s) / span, (new.high_s - old.low_s) / span
        return min(-d, max(slowest, -10.0)), max(d, min(fastest, 1.0))

    def _agrees(self, a: Anchor, now_s: float, diff_s: float, drift: Tuple[float, float]) -> bool:
        """Whether an answer is on the clock of a sample that arrived ``diff_s`` after its stamp (that delay is an
        upper bound on the offset, so an answer whose lower bound is above it is on another clock, and so is one
        whose upper bound is further below it than any delay a link could hold)."""
        age = max(now_s - a.at_s, 0.0)
        return (a.low_s + drift[0] * age <= diff_s + self.config.tolerance_s
                and a.high_s + drift[1] * age >= diff_s - self.config.max_delay_s)

    def bounds_s(self, now_s: float, diff_s: float) -> Optional[Tuple[float, float]]:
        """The lowest and highest offset (s) the newest answers allow at ``now_s``, from those on the clock of a
        sample that arrived ``diff_s`` after its stamp (None without one, or once the clocks disagree). Each
        answer's bounds widen as it ages, as fast as ``drift_bounds`` allow."""
        if self.agreement.why or not self._anchors:
            return None
        low, high, drift = -math.inf, math.inf, self.drift_bounds()
        # The newest answers only: carried forward over seconds at an average rate, older ones would cross the
        # truth when a simulator's lag comes and goes.
        newest_s = self._anchors[-1].at_s
        for a in self._anchors:
            if a.at_s >= newest_s - self.config.period_s and self._agrees(a, now_s, diff_s, drift):
                age = max(now_s - a.at_s, 0.0)
                low, high = max(low, a.low_s + drift[0] * age), min(high, a.high_s + drift[1] * age)
        return None if high == math.inf else (min(low, high), high)

    def on_other_clock(self, now_s: float, diff_s: float) -> bool:
        """True when the newest answer is not on the clock of a sample that arrived ``diff_s`` after its stamp."""
        return bool(self._anchors) and not self._agrees(self._anchors[-1], now_s, diff_s, self.drift_bounds())

    def problem(self, now_s: float) -> str:
        """Why no telemetry may be trusted now ('' when the round trips allow it)."""
        c = self.config
        if self.round_trip_s is not None and self.round_trip_s > c.max_round_trip_s:
            return (f"MAVLink round trip {self.round_trip_s:.2f} s (TIMESYNC): the link cannot deliver telemetry "
                    f"in time (limit {c.max_round_trip_s:g} s)")
        if (self.answered == 0 and self.first_request_s is not None
                and now_s - self.first_request_s < c.first_answer_wait_s):
            return "waiting for the autopilot's first TIMESYNC answer (how late its telemetry arrives)"
        return ""
