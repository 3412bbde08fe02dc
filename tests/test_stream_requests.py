"""Telemetry streams are asked for again when they come slower than asked, and all of them after a reboot."""
from __future__ import annotations

import time

from edge_landing.runtime.io.mavlink_link import LinkConfig, MavlinkLink
from edge_landing.runtime.io.stream_requests import StreamRequestConfig, StreamRequests
from edge_landing.runtime.io.telemetry import TelemetryBuffer
from tests.fake_autopilot import FakeAutopilot
from tests.run_helpers import free_udp_port, wait_for

SET_MESSAGE_INTERVAL, LOCAL_POSITION_NED = 511, 32


def ask_times(streams: StreamRequests, attitude_hz: float, t0_s: float, t1_s: float, reboots: int = 0) -> list:
    """Play ATTITUDE at ``attitude_hz`` from ``t0_s`` to ``t1_s`` in time order, asking ``due`` every 0.1 s (as the
    link does at most every 0.5 s); the times anything was due, with what."""
    out, step = [], 0.01
    next_attitude = t0_s
    for k in range(1, int(round((t1_s - t0_s) / step)) + 1):
        now = round(t0_s + k * step, 6)
        if attitude_hz and now >= next_attitude:
            streams.arrived("ATTITUDE", now)
            next_attitude = now + 1.0 / attitude_hz
        if k % 10 == 0:
            due = streams.due(now, reboots)
            if due:
                out.append((round(now, 1), sorted(n for n, _ in due)))
    return out


def test_a_slow_stream_is_asked_again_with_back_off_and_a_reboot_asks_for_all():
    streams = StreamRequests({"ATTITUDE": 20.0, "DISTANCE_SENSOR": 20.0}, StreamRequestConfig())
    first = streams.due(0.0)
    assert sorted(first) == [("ATTITUDE", 50_000.0), ("DISTANCE_SENSOR", 50_000.0)]   # all at first; interval in µs
    # ATTITUDE comes at its rate and is not asked again; DISTANCE_SENSOR never comes: asked after 3, 6 and 12 s.
    assert ask_times(streams, 20.0, 0.0, 30.0) == [(3.0, ["DISTANCE_SENSOR"]), (9.0, ["DISTANCE_SENSOR"]),
                                                     (21.0, ["DISTANCE_SENSOR"])]
    # ATTITUDE slows to 4/s (the autopilot's stored rate after it forgot ours): asked again as soon as its 2 s
    # window falls below half the rate (1.25 s after), then 3 s later (DISTANCE_SENSOR's next ask is at 45 s).
    assert ask_times(streams, 4.0, 30.0, 40.0) == [(31.3, ["ATTITUDE"]), (34.3, ["ATTITUDE"])]
    # A reboot asks for every stream at once, and starts the back-off over.
    assert ask_times(streams, 4.0, 40.0, 40.1, reboots=1) == [(40.1, ["ATTITUDE", "DISTANCE_SENSOR"])]
    assert ask_times(streams, 4.0, 40.1, 43.0, reboots=1) == []
    assert streams.asked("ATTITUDE") == 4 and streams.asked("DISTANCE_SENSOR") == 5
    # A reboot asks for a stream at its full rate too: the autopilot forgot our interval, and what still comes may
    # be its stored rate, or samples from before the reboot was confirmed.
    assert ask_times(streams, 20.0, 43.0, 50.0, reboots=1) == [(43.1, ["ATTITUDE", "DISTANCE_SENSOR"]),
                                                                (49.1, ["DISTANCE_SENSOR"])]
    assert ask_times(streams, 20.0, 50.0, 50.1, reboots=2) == [(50.1, ["ATTITUDE", "DISTANCE_SENSOR"])]
    # Hysteresis: at 60 % of its rate (between half and three quarters) ATTITUDE is not asked again.
    assert ask_times(streams, 12.0, 50.1, 60.0, reboots=2) == [(53.1, ["DISTANCE_SENSOR"]), (59.1, ["DISTANCE_SENSOR"])]

def test_after_a_reboot_the_position_stream_is_asked_for_again_and_comes_back():
    """A TEST DOUBLE of an autopilot that forgets SET_MESSAGE_INTERVAL when it reboots, as ArduPilot and PX4 do:
    ATTITUDE flows at its stored rate whatever is asked, LOCAL_POSITION_NED only once asked for since boot. Before,
    the link asked again only when no telemetry at all came, so ATTITUDE hid the missing position for good."""
    booted = {"s": 0.0}

    def asked_since_boot(fake: FakeAutopilot) -> bool:
        return any(c.command == SET_MESSAGE_INTERVAL and int(c.param1) == LOCAL_POSITION_NED and t >= booted["s"]
                   for t, c in fake.of_type("COMMAND_LONG"))

    def script(fake: FakeAutopilot, t: float) -> None:
        m, ms = fake.mavutil.mavlink, fake.boot_ms()
        if t >= 4.0 and not booted["s"]:
            fake.reboot()
            booted["s"], ms = time.monotonic(), fake.boot_ms()
        fake.conn.mav.heartbeat_send(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, m.MAV_STATE_ACTIVE)
        fake.conn.mav.attitude_send(ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if asked_since_boot(fake):
            fake.conn.mav.local_position_ned_send(ms, 5.0, -3.0, -10.0, 0.0, 0.0, 0.0)

    port, telemetry = free_udp_port(), TelemetryBuffer()
    with FakeAutopilot(port, script) as fake:
        link = MavlinkLink(LinkConfig(f"udpout:127.0.0.1:{port}"), telemetry).start()
        try:
            def position_now() -> bool:
                state = telemetry.newest_state()
                return state is not None and state.position_ned_m is not None

            assert wait_for(position_now, 5.0), "the first request must start the position stream"
            assert wait_for(lambda: telemetry.reboots == 1, 10.0), "the reboot must be seen"
            assert wait_for(position_now, 8.0), "the position stream must be asked for again and come back"
            assert asked_since_boot(fake)
        finally:
            link.stop()
