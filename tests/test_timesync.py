"""TIMESYNC round trips against a link that delays telemetry (ARCHITECTURE.md §12, "Round trips"): unit tests of
RoundTrips and TelemetryBuffer on a simulated clock, and edge-run against the fake autopilot (a test double that
answers TIMESYNC as ArduPilot does; real pymavlink on both ends)."""
from __future__ import annotations

import math
from typing import Optional, Tuple

import numpy as np
import pytest

from edge_landing.runtime.io.telemetry import TelemetryBuffer
from edge_landing.runtime.io.timesync import RoundTrips, TimeSyncConfig
from tests.fake_autopilot import FakeAutopilot
from tests.test_trust import SWITCH_S, assets, run_against  # noqa: F401  (fixture)
from tests.test_trust_timing import RATE_HZ, feed

BOOT0_S = 5.0     # the autopilot's boot clock when the flight starts
T0_S = 1000.0     # this computer's clock then


def fly(buf: TelemetryBuffer, seconds: float, delay_s: float, answer: bool = True, round_trip_s: float = 0.01,
        tc1_offset_s: float = 0.0, clock_rate: float = 1.0, lags=(0.0, 0.05, 0.15)) -> list:
    """Telemetry at RATE_HZ, each sample delivered ``delay_s`` after it was measured; TIMESYNC requests as edge-run
    sends them,
    answered after ``round_trip_s`` (``tc1`` on the boot clock plus ``tc1_offset_s``). Returns, per lookup,
    (seconds since the start, the match) for frames captured just now and a little before."""
    dt = 1.0 / RATE_HZ
    every = max(int(round(TimeSyncConfig().period_s * RATE_HZ)), 1)
    pending: list = []          # (answer due, tc1 ns, ts1)
    out = []
    for i in range(int(seconds * RATE_HZ)):
        now = T0_S + i * dt
        boot = BOOT0_S + (i * dt - delay_s) * clock_rate
        if i % every == 0:
            ts1 = buf.timesync_request(now)
            received = now + round_trip_s / 2
            tc1 = int((BOOT0_S + (received - T0_S) * clock_rate + tc1_offset_s) * 1e9)
            pending.append((now + round_trip_s, tc1, ts1))
        for due, tc1, ts1 in [p for p in pending if p[0] <= now]:
            if answer:
                buf.timesync_reply(tc1, ts1, due)
        pending = [p for p in pending if p[0] > now]
        if boot > 0:
            feed(buf, boot, now)
        out += [(i * dt, buf.lookup(now - lag, now)) for lag in lags]
    return out


def fresh_share(matches: list, after_s: float = 0.0, before_s: float = 1e9) -> float:
    chosen = [m.fresh for t, m in matches if after_s <= t < before_s]
    assert chosen
    return sum(chosen) / len(chosen)


def test_telemetry_delayed_steadily_from_the_start_is_refused_once_the_autopilot_answers():
    """Every sample 2 s old when it arrives, from the first one: one-way time stamps take the delay for the clock
    offset, and every frame matched "fresh" 2 s old telemetry (the control below). The round trips show it."""
    matches = fly(TelemetryBuffer(), 10.0, delay_s=2.0)
    assert fresh_share(matches) == 0.0
    reasons = {m.reason.split(" (")[0] for _, m in matches}
    assert any("TIMESYNC" in m.reason and "2.0 s" in m.reason for _, m in matches[int(3 * RATE_HZ):]), reasons
    unanswered = fly(TelemetryBuffer(), 10.0, delay_s=2.0, answer=False)
    assert fresh_share(unanswered, after_s=2.0) > 0.95          # the limitation the round trips remove


@pytest.mark.parametrize("delay_s", [0.0, 0.02, 0.1])
def test_a_healthy_link_that_answers_keeps_its_telemetry(delay_s):
    matches = fly(TelemetryBuffer(), 10.0, delay_s=delay_s, lags=(0.0, 0.05))
    assert fresh_share(matches, after_s=0.1) > 0.97
    assert "waiting for the autopilot's first TIMESYNC answer" in matches[0][1].reason   # before the first answer


@pytest.mark.parametrize("clock_rate", [0.95, 0.8, 0.5, 2.0])
def test_a_lagging_simulator_s_clock_is_followed_when_it_answers(clock_rate):
    """A SITL that lags behind real time: its clock, its telemetry's stamps and its TIMESYNC answers all run slow
    (or fast: sped up). One-way stamps follow a slow one only up to max_drift (10 %: the control); the answers'
    lower bound follows it."""
    matches = fly(TelemetryBuffer(), 20.0, delay_s=0.01, clock_rate=clock_rate, lags=(0.0, 0.05))
    assert fresh_share(matches, after_s=4.0) > 0.97
    if clock_rate < 0.9:
        unanswered = fly(TelemetryBuffer(), 20.0, delay_s=0.01, clock_rate=clock_rate, answer=False, lags=(0.0,))
        assert fresh_share(unanswered, after_s=4.0) < 0.05


@pytest.mark.parametrize("clock_rate", [1.0, 0.7])
def test_late_bursts_stay_old_when_the_autopilot_answers(clock_rate):
    """Telemetry held back and delivered 0.7-1.7 s late in bursts (tests/test_trust_timing.py), TIMESYNC answered
    at once, on a normal and on a slow clock: the bounds that follow a slow clock do not make late samples fresh."""
    buf, dt = TelemetryBuffer(), 1.0 / RATE_HZ
    every = max(int(round(TimeSyncConfig().period_s * RATE_HZ)), 1)
    pending: list = []
    fresh_late = 0
    for i in range(int(12 * RATE_HZ)):
        now = T0_S + i * dt
        boot = BOOT0_S + i * dt * clock_rate
        if i % every == 0:
            buf.timesync_reply(int((boot + 0.005) * 1e9), buf.timesync_request(now), now + 0.01)
        if i * dt < 6.0:
            feed(buf, boot, now)
            continue
        pending.append(boot)
        if i % int(RATE_HZ) == 0:
            ready = [b for b in pending if (boot - b) >= 0.7 * clock_rate]
            pending = [b for b in pending if (boot - b) < 0.7 * clock_rate]
            for b in ready:
                feed(buf, b, now)
        fresh_late += i * dt >= 6.5 and sum(buf.lookup(now - lag, now).fresh for lag in (0.0, 0.05, 0.15))
    assert fresh_late == 0


def fly_clocks(seconds: float, rate_at=lambda t: 1.0, answers_rate: Optional[float] = None,
               reboot_at_s: Optional[float] = None) -> Tuple[list, TelemetryBuffer]:
    """On-time telemetry from an autopilot clock running at ``rate_at(t)`` × real time; its TIMESYNC answers on the
    same clock, or (a test double's inconsistency) on one running at ``answers_rate``, or one that does not restart
    when the telemetry's does at ``reboot_at_s``. Returns (time, fresh) per frame captured now, and the buffer."""
    buf, dt = TelemetryBuffer(), 1.0 / RATE_HZ
    every = max(int(round(TimeSyncConfig().period_s * RATE_HZ)), 1)
    boot = answers_clock = BOOT0_S
    out = []
    for i in range(int(seconds * RATE_HZ)):
        t, now = i * dt, T0_S + i * dt
        boot += dt * rate_at(t)
        answers_clock += dt * (rate_at(t) if answers_rate is None else answers_rate)
        if reboot_at_s is not None and abs(t - reboot_at_s) < dt / 2:
            boot = 0.5
        if i % every == 0:
            buf.timesync_reply(int((answers_clock + 0.005) * 1e9), buf.timesync_request(now), now + 0.01)
        feed(buf, boot - 0.01, now)
        out.append((t, buf.lookup(now, now).fresh))
    return out, buf


@pytest.mark.parametrize("name, rate_at", [("lag that comes and goes", lambda t: 0.6 if int(t) % 6 < 3 else 1.0),
                                           ("lag swinging 0.4-1.0", lambda t: 0.7 + 0.3 * math.sin(t)),
                                           ("lag growing to half speed", lambda t: max(0.5, 1.0 - 0.05 * t))])
def test_a_simulator_s_lag_that_changes_is_followed(name, rate_at):
    out, buf = fly_clocks(30.0, rate_at)
    assert np.mean([f for t, f in out if t >= 1.0]) > 0.97, name
    assert buf._clock.round_trips.agreement.why == ""          # one clock: the answers stay trusted


@pytest.mark.parametrize("answers_rate", [1.0, 1.05])
def test_a_double_whose_answers_run_on_another_clock_is_not_believed(answers_rate):
    """A test double whose telemetry stamps run 2 % slow (or 5 % fast) against its TIMESYNC answers' clock: the gap
    between them drifts steadily, which one clock cannot do; its answers are ignored and its telemetry is timed by
    its stamps alone, as before round trips (its drift is within max_drift)."""
    out, buf = fly_clocks(30.0, lambda t: 0.98 if answers_rate == 1.0 else 1.0, answers_rate=answers_rate)
    assert np.mean([f for t, f in out if t >= 1.0]) > 0.97
    assert "drift" in buf._clock.round_trips.agreement.why


def test_a_double_whose_answers_do_not_restart_with_its_telemetry_is_not_believed():
    out, buf = fly_clocks(20.0, reboot_at_s=6.0)
    assert "did not restart" in buf._clock.round_trips.agreement.why
    assert np.mean([f for t, f in out if t >= 10.0]) > 0.97


def test_an_answer_on_another_clock_is_ignored_not_trusted():
    """tc1 counted from 1970 (a component whose TIMESYNC is not its boot clock): it says nothing about the
    telemetry's clock, so it neither caps the offset nor blocks telemetry; it is counted."""
    buf = TelemetryBuffer()
    matches = fly(buf, 6.0, delay_s=0.02, tc1_offset_s=1.7e9, lags=(0.0,))
    assert fresh_share(matches, after_s=0.1) > 0.97
    assert buf.rejected().get("TIMESYNC answer on another clock than the telemetry's (ignored)", 0) >= 5


def test_a_long_round_trip_refuses_telemetry_until_a_short_one():
    c = TimeSyncConfig()
    trips = RoundTrips(c)
    first = trips.request(10.0)
    assert trips.problem(10.5).startswith("waiting")
    assert trips.reply(int(5e9), first, 10.01) and trips.problem(10.5) == ""
    assert not trips.reply(int(5e9), first, 10.02)                # the same answer again: matched once only
    assert not trips.reply(int(5e9), trips.request(10.6), 10.59)  # "answered" before it was asked
    slow = trips.request(11.0)
    assert trips.reply(int(6.5e9), slow, 11.0 + c.max_round_trip_s + 0.5)
    assert "round trip 1.50 s" in trips.problem(12.6)
    fast = trips.request(13.0)
    assert not trips.reply(int(8e9), fast + 1, 13.01)            # an answer to no request of ours changes nothing
    assert trips.problem(13.1) != ""
    assert trips.reply(int(8e9), fast, 13.01) and trips.problem(13.1) == ""


def test_an_autopilot_that_never_answers_is_trusted_as_before_after_the_wait():
    c = TimeSyncConfig()
    matches = fly(TelemetryBuffer(), 4.0, delay_s=0.02, answer=False, lags=(0.0,))
    assert fresh_share(matches, before_s=c.first_answer_wait_s) == 0.0
    assert fresh_share(matches, after_s=c.first_answer_wait_s + 0.1) == 1.0


def test_a_reboot_forgets_the_old_clock_s_bounds():
    """The autopilot reboots (its clock restarts, and its TIMESYNC answers with it): the old answers' bounds would
    put every new sample seconds in the past; they are dropped with the old clock."""
    buf, dt = TelemetryBuffer(), 1.0 / RATE_HZ
    fly(buf, 4.0, delay_s=0.02)
    fresh = []
    for i in range(int(8 * RATE_HZ)):
        now = T0_S + 4.0 + i * dt
        boot = 0.5 + i * dt                                      # a new boot clock
        if i % int(RATE_HZ) == 0:
            buf.timesync_reply(int((boot + 0.005) * 1e9), buf.timesync_request(now), now + 0.01)
        feed(buf, boot, now + 0.02)
        fresh.append(buf.lookup(now, now + 0.02).fresh)
    assert buf.rejected().get("autopilot rebooted (its clock restarted): every earlier sample dropped", 0) >= 1
    assert sum(fresh[-int(4 * RATE_HZ):]) > 0.95 * 4 * RATE_HZ


def test_requests_without_answers_cannot_grow_memory():
    trips = RoundTrips(TimeSyncConfig())
    for i in range(10_000):
        trips.request(i * 0.01)
    assert len(trips._pending) <= TimeSyncConfig().max_pending


def test_edge_run_sends_nothing_from_telemetry_delivered_two_seconds_late_from_the_start(assets, tmp_path):  # noqa: F811
    """The whole flight's telemetry reaches edge-run 2 s after it was measured (a buffering radio), the fake
    autopilot answers TIMESYNC at once: no target. Before the round trips, every frame got one."""
    def script(fake: FakeAutopilot, t: float) -> None:
        fake.healthy(boot_ms=fake.boot_ms() - 2000)

    fake, decisions, _ = run_against(assets, tmp_path, script, 4.0)
    assert decisions and fake.of_type("LANDING_TARGET") == []
    assert fake.of_type("TIMESYNC"), "edge-run sent no TIMESYNC request"
    assert any("TIMESYNC" in d["reason"] for d in decisions), {d["reason"] for d in decisions}


def test_edge_run_answers_timesync_and_sends_targets_when_the_link_is_healthy(assets, tmp_path):  # noqa: F811
    answers: list = []

    def script(fake: FakeAutopilot, t: float) -> None:
        fake.healthy()
        if not fake.__dict__.get("asked"):
            fake.__dict__["asked"] = True
            fake.conn.mav.timesync_send(0, 123456789)            # the autopilot's own request
            for k in range(200):                                 # then a flood of them
                fake.conn.mav.timesync_send(0, 1000 + k)
        answers.extend(m for _, m in fake.of_type("TIMESYNC") if m.tc1 != 0 and m.ts1 == 123456789)

    fake, _, _ = run_against(assets, tmp_path, script, 3.5)
    assert len(fake.targets_between(1.5, 1e9)) >= 5
    assert answers, "edge-run did not answer the autopilot's TIMESYNC request"
    flood = [m for _, m in fake.of_type("TIMESYNC") if m.tc1 != 0 and 1000 <= m.ts1 < 1200]
    assert len(flood) <= 5                                       # answered at most 20 times a second

