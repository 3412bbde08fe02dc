"""Telemetry timing against a misbehaving autopilot (ARCHITECTURE.md §12, fresh telemetry and the clock offset):
late bursts, a frozen clock, a flood, a reboot. Unit tests of TelemetryBuffer, and one edge-run run against the
fake autopilot (a test double, real pymavlink on both ends)."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

from edge_landing.runtime.io.telemetry import ClockOffset, TelemetryBuffer, TelemetryConfig
from tests.fake_autopilot import FakeAutopilot
from tests.test_trust import SWITCH_S, assert_healthy_phase_sent, assets, run_against  # noqa: F401  (fixture)

RATE_HZ = 20.0


def feed(buf: TelemetryBuffer, boot_s: float, arrival_s: float, yaw: float = 0.0) -> None:
    ms = boot_s * 1000.0
    buf.add_attitude(0.0, 0.0, yaw, ms, arrival_s)
    buf.add_position(5.0, -3.0, -10.0, ms, arrival_s)
    buf.add_relative_alt(10.0, ms, arrival_s)


def test_telemetry_held_back_and_delivered_in_bursts_is_never_fresh():
    """Healthy for 3 s, then for 4 s every sample is delivered 0.7-1.7 s after it was measured, in a burst once a
    second. Each burst makes the attitude's arrival recent, but what it says is 0.7 s old or more: no frame captured
    then may match it. ArduPilot's JitterCorrection (and this runtime before) moved a sample more than 0.5 s late
    forward to 0.5 s, and the offset with it, so the burst's newer samples were mapped onto their arrival. (Bursts
    that go on for longer than (0.7 - window_s) / max_drift = 4.5 s are taken for a slow clock, see below.)"""
    buf, t0 = TelemetryBuffer(), 1000.0
    dt = 1.0 / RATE_HZ
    fresh_late, fresh_healthy = 0, 0
    pending: list = []
    for i in range(int(7 * RATE_HZ)):
        now = t0 + i * dt
        boot = 5.0 + i * dt
        if now - t0 < SWITCH_S:
            feed(buf, boot, now)
            fresh_healthy += buf.lookup(now, now).fresh
            continue
        pending.append(boot)
        if i % int(RATE_HZ) == 0:                       # once a second: everything measured 0.7 s ago or earlier
            ready = [b for b in pending if (boot - b) >= 0.7]
            pending = [b for b in pending if (boot - b) < 0.7]
            for b in ready:
                feed(buf, b, now)
        for lag in (0.0, 0.05, 0.15):                  # frames captured just now and a little before
            # (the last healthy sample, measured at SWITCH_S, is itself fresh for fresh_s)
            fresh_late += now - t0 >= SWITCH_S + 0.5 and buf.lookup(now - lag, now).fresh
    assert fresh_healthy > 0.9 * SWITCH_S * RATE_HZ     # not vacuous
    assert fresh_late == 0


def test_a_link_that_turns_slow_is_not_taken_for_a_slow_clock_at_once():
    """Every sample 0.8 s late from 3 s on (a link that turned slow): the offset rises only as fast as clocks drift
    (max_drift), so the late samples are not matched as fresh for (0.8 - 0.25 s) / max_drift; a one-way timestamp
    cannot tell a lasting delay from a slow clock for ever (ARCHITECTURE.md §12)."""
    c = TelemetryConfig()
    clock = ClockOffset(c)
    ages = []
    for i in range(int(20 * RATE_HZ)):
        t = 100.0 + i / RATE_HZ
        arrival = t + (0.8 if t >= 103.0 else 0.0)
        local = clock.map(5.0 + i / RATE_HZ, arrival)
        assert local is not None
        ages.append((t - 100.0, arrival - local))
    late = [age for when, age in ages if 3.0 <= when < 3.0 + (0.8 - c.window_s) / c.max_drift]
    assert late and min(late) > c.window_s           # was 0.5 s at once, then 0.0 after one window


def test_a_slow_autopilot_clock_is_still_followed():
    """5 % slow for 30 s: the offset keeps up (the drift bound is not a freeze)."""
    clock = ClockOffset(TelemetryConfig())
    for i in range(int(30 * RATE_HZ)):
        arrival = 1000.0 + i / RATE_HZ
        local = clock.map(5.0 + 0.95 * i / RATE_HZ, arrival)
        assert local is not None and arrival - 0.25 <= local <= arrival + 1e-9, (i, arrival - local)


@pytest.mark.parametrize("ahead_s", [0.12, 0.3, 0.45])
def test_one_sample_stamped_a_little_in_the_future_costs_no_telemetry(ahead_s):
    """One ATTITUDE stamped 0.3-0.45 s ahead was adopted as the new offset: every later sample then lay that far in
    the past, beyond the matching window, and no frame had telemetry for 2.7 s. Now it is dropped (beyond
    max_future_s) or only shifts the matching by less than the window."""
    buf, t0 = TelemetryBuffer(), 1000.0
    lost = 0
    for i in range(int(20 * RATE_HZ)):
        now = t0 + i / RATE_HZ
        if i == 60:
            buf.add_attitude(0.0, 0.0, 0.0, (5.0 + i / RATE_HZ + ahead_s) * 1000.0, now)
        feed(buf, 5.0 + i / RATE_HZ, now)
        lost += not buf.lookup(now, now).fresh
    assert lost == 0


def test_a_frozen_autopilot_clock_gives_no_match():
    """time_boot_ms stops while the values keep changing: new values under an old time are not matched to frames
    captured later (they are counted), so telemetry goes stale instead of being placed at a wrong time."""
    buf, t0 = TelemetryBuffer(), 1000.0
    for i in range(int(8 * RATE_HZ)):
        now = t0 + i / RATE_HZ
        boot = 5.0 + min(i / RATE_HZ, 3.0)              # frozen from 3 s on
        feed(buf, boot, now, yaw=0.3 * math.sin(i / 5.0))
        if now - t0 >= 4.0:
            assert not buf.lookup(now, now).fresh, now - t0
        elif now - t0 < 3.0:
            assert buf.lookup(now, now).fresh
    assert any(k.startswith("sample not newer than the last one") for k in buf.rejected())


def test_a_flood_of_samples_cannot_grow_memory():
    buf = TelemetryBuffer()
    for i in range(20000):                               # 20000 attitudes within 2 s
        buf.add_attitude(0.0, 0.0, 0.0, 5000.0 + i * 0.1, 1000.0 + i * 1e-4)
    assert len(buf._attitude.times) <= TelemetryConfig().max_samples
    assert buf.lookup(1002.0, 1002.0).fresh


def test_a_reboot_drops_every_earlier_sample():
    """After a reboot nothing from the old estimator (or its clock offset) is interpolated with the new one's."""
    buf, t0 = TelemetryBuffer(), 1000.0
    for i in range(40):
        feed(buf, 600.0 + i / RATE_HZ, t0 + i / RATE_HZ, yaw=0.0)
    for i in range(45):                                    # rebooted 3 s ago, turned to 1 rad; confirmed after 2 s
        buf.add_attitude(0.0, 0.0, 1.0, 3000.0 + 50 * i, t0 + 2.3 + i / RATE_HZ)
    state = buf.state_at(t0 + 2.1)                         # between the last old and the first new sample
    assert state is None or state.attitude.yaw_rad == 1.0          # was 0.67: interpolated across the reboot
    assert buf.newest_state().position_epoch == 1 and buf.newest_state().agl_m is None


def test_one_replayed_old_sample_is_dropped_not_taken_for_a_reboot():
    """Three samples measured 3 s ago arrive again (a router's buffer, a replayed log) between healthy ones: they
    are dropped and counted. Taking them for a reboot mapped them onto their arrival, as fresh, dropped the next
    2 s of healthy telemetry as 'from the future' and dropped the committed spot."""
    buf, t0 = TelemetryBuffer(), 1000.0
    for i in range(int(6 * RATE_HZ)):
        now = t0 + i / RATE_HZ
        if i == int(3 * RATE_HZ):
            for k in range(3):                             # tilted and 20 m higher, 3 s ago
                ms = (5.0 + i / RATE_HZ - 3.0) * 1000.0 + 50 * k
                buf.add_attitude(0.4, 0.0, 0.0, ms, now)
                buf.add_relative_alt(30.0, ms, now)
        feed(buf, 5.0 + i / RATE_HZ, now)
        match = buf.lookup(now, now)
        assert match.fresh and match.state.agl_m == 10.0 and match.state.attitude.roll_rad == 0.0, now - t0
    assert match.state.position_epoch == 0
    assert buf.rejected() == {"sample stamped seconds before the last one (replayed, or a reboot not yet confirmed)": 6}


def test_a_reboot_soon_after_boot_is_confirmed_too():
    """The old clock had run 3.5 s: the restarted one passes its last time stamp within the confirmation window,
    yet it is still 3.5 s behind the clock followed so far, so the reboot is confirmed and telemetry comes back."""
    buf, t0 = TelemetryBuffer(), 1000.0
    for i in range(int(8 * RATE_HZ)):
        now = t0 + i / RATE_HZ
        boot = 3.5 + i / RATE_HZ if now - t0 < 3.0 else 0.001 + (now - t0 - 3.0)
        feed(buf, boot, now)
        match = buf.lookup(now, now)
        if 3.5 <= now - t0 < 5.0:
            assert not match.fresh                          # confirming: the new clock's samples are dropped
        if now - t0 >= 5.5:
            assert match.fresh and match.state.position_epoch == 1, now - t0


def test_edge_run_keeps_its_spot_through_one_replayed_old_sample(assets, tmp_path):  # noqa: F811
    """Three samples measured 3 s ago (tilted, 30 m up) arrive once between healthy ones. Before, they were taken
    for a reboot: mapped onto their arrival as fresh (fusion ran on them), the committed spot dropped, and the
    next 1.8 s of healthy telemetry dropped as 'from the future'."""
    def script(fake: FakeAutopilot, t: float) -> None:
        if t >= SWITCH_S and not fake.__dict__.get("replayed"):
            fake.__dict__["replayed"] = True
            for k in range(3):
                fake.healthy(boot_ms=fake.boot_ms() - 3000 + 50 * k, roll=0.4, ned=(5.0, -3.0, -30.0))
        fake.healthy()

    fake, decisions, _ = run_against(assets, tmp_path, script, 5.0)
    assert_healthy_phase_sent(fake)
    assert len(fake.targets_between(SWITCH_S, 1e9)) >= 5
    assert not any("spot dropped" in text or "telemetry lost" in text for text in fake.texts()), fake.texts()
    assert all(d["agl_m"] in (None, 10.0) for d in decisions)


def test_edge_run_sends_nothing_from_telemetry_delivered_late_in_bursts(assets, tmp_path):  # noqa: F811
    """The same bursts through pymavlink: before the fix 99 targets went out in 3 s from 0.7-1.7 s old telemetry."""
    def script(fake: FakeAutopilot, t: float) -> None:
        if t < SWITCH_S:
            fake.healthy()
            return
        queue = fake.__dict__.setdefault("late", [])
        now = time.monotonic()
        queue.append((now, fake.boot_ms()))
        if now >= fake.__dict__.get("next_burst", 0.0):
            fake.__dict__["next_burst"] = now + 1.0
            fake.__dict__["late"] = [q for q in queue if now - q[0] < 0.7]
            for _, ms in (q for q in queue if now - q[0] >= 0.7):
                fake.healthy(boot_ms=ms)

    fake, decisions, _ = run_against(assets, tmp_path, script, 6.0)
    assert_healthy_phase_sent(fake)
    assert fake.targets_between(SWITCH_S + 0.5, 1e9) == []
    assert any("telemetry lost" in text for text in fake.texts())
    late = [d for d in decisions if d["capture_time_s"] > fake.heard_s + SWITCH_S + 1.0]
    assert late and not any(d["sent"] for d in late)
    assert np.mean([d["reason"].startswith("held:") for d in late]) == 1.0


@pytest.mark.parametrize("late_s", [0.2, 0.4])
def test_fast_samples_after_a_starved_window_are_adopted_at_once(late_s):
    """The receiving thread held up for a whole window (a loaded companion): every sample of the window arrives
    ``late_s`` late, the offset rises, and the link's next samples, on time again, look "from the future" against
    it. The link showed it can do that in the windows before, so they are adopted at once: dropping them as
    glitches cost a window of telemetry. (At start-up there is no such history: a future sample is dropped, as a
    glitch 1.9 s ahead must be, tests/test_trust.py.)"""
    for starved_from_s, starved_s in ((6.0, 2.5), (6.5, 4.5)):   # over one window, over two
        buf, t0 = TelemetryBuffer(), 1000.0
        stale = 0
        for i in range(int(12 * RATE_HZ)):
            t = i / RATE_HZ
            late = late_s if starved_from_s <= t < starved_from_s + starved_s else 0.0
            feed(buf, 5.0 + t, t0 + t + late)
            if t >= starved_from_s + starved_s + 0.2:   # on time again (and one sample to learn it)
                stale += not buf.lookup(t0 + t, t0 + t).fresh
        assert stale == 0, (starved_from_s, stale)


def test_a_sample_without_a_time_stamp_is_dropped_not_stamped_on_arrival():
    """time_boot_ms = 0 from the link: stamped on arrival, held-back telemetry would look fresh."""
    buf = TelemetryBuffer()
    assert not buf.add_attitude(0.0, 0.0, 0.0, 0, 1000.0)
    assert not buf.add_attitude(0.0, 0.0, 0.0, math.nan, 1000.1)
    assert not buf.lookup(1000.1, 1000.1).fresh
    assert any(k.startswith("sample without a time stamp") for k in buf.rejected())
    assert buf.add_attitude(0.0, 0.0, 0.0, None, 1000.2)    # a caller without autopilot time: its arrival


def test_a_stream_that_stops_while_attitude_flows_gives_frames_none_of_its_quantity():
    """Freshness is judged on the newest attitude, but every quantity is matched on its own near the capture time:
    when LOCAL_POSITION_NED and the height stop while ATTITUDE keeps coming (a stream the autopilot dropped), frames
    are still fresh, yet a capture time past the last position by more than the matching window gets no position
    and no height, never the last ones held (nothing is then placed in, or re-expressed from, local NED)."""
    buf, t0, dt = TelemetryBuffer(), 1000.0, 1.0 / RATE_HZ
    for i in range(int(3 * RATE_HZ)):
        now, ms = t0 + i * dt, (5.0 + i * dt) * 1000.0
        buf.add_attitude(0.0, 0.0, 0.3, ms, now)
        if i < RATE_HZ:                                       # position and height for the first second only
            buf.add_position(5.0, -3.0, -10.0, ms, now, velocity_ned_mps=(0.0, 0.0, 0.0))
            buf.add_relative_alt(10.0, ms, now)
    now = t0 + 3 * dt * RATE_HZ - dt
    early = buf.lookup(t0 + 0.5, now_s=now)
    assert early.state is not None and early.state.position_ned_m is not None and early.state.agl_m == 10.0
    c = buf.config
    last_position_s = t0 + (RATE_HZ - 1) * dt
    for capture in (last_position_s + c.window_s + 0.01, now):   # just past the matching window, and much later
        late = buf.lookup(capture, now_s=now)
        assert late.state is not None, late.reason                 # the attitude is fresh: the frame is usable
        assert late.state.position_ned_m is None and late.state.agl_m is None
    assert buf.newest_state() is not None and buf.newest_state().position_ned_m is None
