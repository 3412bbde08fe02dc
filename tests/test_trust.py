"""The trust rules of ARCHITECTURE.md §12 against a misbehaving autopilot (a test double, real pymavlink on both ends).

Every test has a healthy phase that does send targets (so the test is not vacuous) and a dangerous phase
that must send no target, or only the right one, from 1 s after it starts (the issue's bound: no target
leaves later than 1 s after the last good telemetry sample).
"""
from __future__ import annotations

import logging
import math
from typing import Tuple

import numpy as np
import pytest

from edge_landing.cli.run import main
from tests.fake_autopilot import FakeAutopilot
from tests.run_helpers import flat_assets, free_tcp_port, free_udp_port, read_decisions

AGL_M = 10.0
SWITCH_S = 3.0          # script time at which the dangerous phase starts
GRACE_S = 1.0           # no target may arrive later than this after the last good telemetry


@pytest.fixture(scope="module")
def assets(tmp_path_factory):
    return flat_assets(tmp_path_factory.mktemp("trust"), AGL_M)


def run_against(assets, tmp_path, script, duration_s: float = 5.5, *extra: str, tcp: bool = False
                ) -> Tuple[FakeAutopilot, list, str]:
    # Random video frames of a flat-ground model while hovering: motion geometry has nothing to confirm, so
    # these trust-rule runs send (and commit) network-only spots with the explicit flag (ARCHITECTURE.md §11).
    port = free_tcp_port() if tcp else free_udp_port()
    log_path = tmp_path / "decisions.jsonl"
    with FakeAutopilot(port, script, tcp=tcp) as fake:
        url = f"tcp:127.0.0.1:{port}" if tcp else f"udpout:127.0.0.1:{port}"
        assert main(["--camera", assets["video"], "--model", assets["model"], "--loop", "--duration", str(duration_s),
                     "--mav", url, "--log", str(log_path), "--allow-unconfirmed", *extra]) == 0
    return fake, read_decisions(log_path), log_path.read_text()


def healthy_then(bad):
    """Healthy telemetry until SWITCH_S, then ``bad(fake, t)``."""
    def script(fake: FakeAutopilot, t: float) -> None:
        if t < SWITCH_S:
            fake.healthy()
        else:
            bad(fake, t)
    return script


def assert_healthy_phase_sent(fake: FakeAutopilot, n: int = 5) -> list:
    good = fake.targets_between(0.0, SWITCH_S)
    assert len(good) >= n, f"the healthy phase sent only {len(good)} targets"
    for t in good:
        assert t.frame == 12 and t.z == pytest.approx(AGL_M, abs=0.3) and t.x > 0
    return good


def test_silent_autopilot_means_no_target_and_it_is_announced(assets, tmp_path, capsys):
    fake, decisions, _ = run_against(assets, tmp_path, healthy_then(lambda f, t: None))
    out = capsys.readouterr().out
    assert "telemetry STALE" in out and "target: none (held: telemetry stale" in out  # the status line says why
    assert_healthy_phase_sent(fake)
    assert fake.targets_between(SWITCH_S + GRACE_S, 1e9) == []
    assert any("telemetry lost" in text for text in fake.texts())
    late = [d for d in decisions if not d["sent"] and d["reason"].startswith("held: telemetry stale")]
    assert late, "frames in the silent phase must say which rule held the target back"


def test_clock_glitch_and_a_slow_autopilot_clock_keep_telemetry(assets, tmp_path):
    def script(fake: FakeAutopilot, t: float) -> None:
        fake.clock_rate = 0.95                      # 5 % slow: 0.3 s behind after 6 s (the match window is 0.25 s)
        ms = fake.boot_ms()                         # (its TIMESYNC answers run on the same slow clock)
        fake.healthy(boot_ms=ms)
        if 1.0 <= t < 1.04:                          # one ATTITUDE stamped 1.9 s in the future
            fake.conn.mav.attitude_send(ms + 1900, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    fake, decisions, _ = run_against(assets, tmp_path, script, 7.0)
    late = fake.targets_between(5.5, 1e9)
    assert len(late) >= 5, "telemetry must still match frames after the glitch and 6 s of drift"
    assert all(t.z == pytest.approx(AGL_M, abs=0.3) for t in late)
    assert sum(d["telemetry"] for d in decisions) > 0.7 * len(decisions)


def test_non_finite_attitude_with_a_downward_rangefinder_never_crashes(assets, tmp_path, caplog, capsys):
    def bad(fake: FakeAutopilot, t: float) -> None:
        ms = fake.boot_ms()
        value = math.nan if int(t * 10) % 2 else math.inf
        fake.conn.mav.heartbeat_send(2, 3, 0, 0, 4)
        fake.conn.mav.attitude_send(ms, value, value, value, 0.0, 0.0, 0.0)
        fake.conn.mav.distance_sensor_send(ms, 20, 4000, 1000, 0, 0, 25, 0)

    with caplog.at_level(logging.WARNING):
        fake, decisions, _ = run_against(assets, tmp_path, healthy_then(bad))
    assert_healthy_phase_sent(fake)
    assert fake.targets_between(SWITCH_S + GRACE_S, 1e9) == []
    frames = [d["frame"] for d in decisions]
    assert frames == list(range(len(frames))), "every frame must reach --log"
    assert not [r for r in caplog.records if r.exc_info], "no traceback"
    out = capsys.readouterr().out
    assert "attitude not finite" in out  # the summary counts the rejected samples by reason


def test_telemetry_from_one_autopilot_only(assets, tmp_path):
    def script(fake: FakeAutopilot, t: float) -> None:
        other = fake.mavutil.mavlink.MAVLink(fake.conn, srcSystem=2, srcComponent=1)
        if t < SWITCH_S:
            fake.healthy()  # the first autopilot HEARTBEAT heard names the autopilot (or --mav-target-system)
        # A second vehicle, tilted, 15 m higher and elsewhere, mixed in all the time.
        fake.healthy(roll=0.5, ned=(40.0, 20.0, -25.0), mav=other)

    fake, decisions, _ = run_against(assets, tmp_path, script)
    good = assert_healthy_phase_sent(fake)
    assert all(abs(t.y) < 0.3 for t in good)      # level: the other vehicle's roll was not used
    assert fake.targets_between(SWITCH_S + GRACE_S, 1e9) == []


def test_an_antenna_tracker_heard_first_is_not_taken_for_the_autopilot(assets, tmp_path):
    """ArduPilot's AntennaTracker firmware says ArduPilot in its HEARTBEAT and streams its own ATTITUDE."""
    def script(fake: FakeAutopilot, t: float) -> None:
        m = fake.mavutil.mavlink
        tracker = m.MAVLink(fake.conn, srcSystem=2, srcComponent=1)
        tracker.heartbeat_send(m.MAV_TYPE_ANTENNA_TRACKER, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, m.MAV_STATE_ACTIVE)
        tracker.attitude_send(fake.boot_ms(), 0.5, 0.3, 0.0, 0.0, 0.0, 0.0)
        if t >= 0.5:
            fake.healthy()

    fake, _, _ = run_against(assets, tmp_path, script, 3.0)
    good = fake.targets_between(0.0, 1e9)
    assert len(good) >= 5, "the vehicle heard after the tracker must still be the autopilot"
    assert all(abs(t.y) < 0.3 and t.z == pytest.approx(AGL_M, abs=0.3) for t in good)   # level: not the tracker's


def test_a_recorded_video_sends_no_target_to_an_armed_autopilot(assets, tmp_path):
    """A video file is another flight's view, placed with this vehicle's live telemetry: the places it names are
    not here. Sent while the autopilot is disarmed (the bench tests above), held once it arms."""
    def script(fake: FakeAutopilot, t: float) -> None:
        fake.armed = t >= SWITCH_S
        fake.healthy()

    fake, decisions, _ = run_against(assets, tmp_path, script)
    assert_healthy_phase_sent(fake)
    assert fake.targets_between(SWITCH_S + 0.5, 1e9) == []
    held = [d for d in decisions if d["not_sent_because"].startswith("held: the autopilot is armed")]
    assert held and "recorded video" in held[0]["not_sent_because"]
    assert any("replay targets held" in text for text in fake.texts())


def test_named_autopilot_that_is_not_there_gives_no_target(assets, tmp_path):
    fake, decisions, _ = run_against(assets, tmp_path, lambda f, t: f.healthy(), 2.0, "--mav-target-system", "42")
    assert fake.of_type("HEARTBEAT") and fake.of_type("LANDING_TARGET") == []
    assert decisions and all(d["reason"].startswith("held: no telemetry") for d in decisions)
    # The same autopilot, unnamed: targets (not vacuous).
    fake, _, _ = run_against(assets, tmp_path, lambda f, t: f.healthy(), 2.0)
    assert len(fake.of_type("LANDING_TARGET")) >= 5


@pytest.mark.parametrize("attitude", [(math.pi, 0.0, 0.0), (0.0, 0.0, 1e30), (0.0, -2.0, 0.0)])
def test_implausible_attitude_is_rejected(assets, tmp_path, attitude):
    def bad(fake: FakeAutopilot, t: float) -> None:
        ms = fake.boot_ms()
        fake.conn.mav.heartbeat_send(2, 3, 0, 0, 4)
        fake.conn.mav.attitude_send(ms, *attitude, 0.0, 0.0, 0.0)
        fake.conn.mav.local_position_ned_send(ms, 5.0, -3.0, -10.0, 0.0, 0.0, 0.0)
        fake.conn.mav.global_position_int_send(ms, 0, 0, 0, 10000, 0, 0, 0, 0)

    fake, _, _ = run_against(assets, tmp_path, healthy_then(bad))
    assert_healthy_phase_sent(fake)
    assert fake.targets_between(SWITCH_S + GRACE_S, 1e9) == []


def test_unknown_height_above_ground_sends_only_the_committed_spot(assets, tmp_path):
    """Negative relative altitude, and a rangefinder beyond its own maximum: no metric scale, so fusion gives
    no new target; only the committed spot (the right one) is re-sent, then dropped after --hold."""
    def bad(fake: FakeAutopilot, t: float) -> None:
        fake.healthy(rel_alt_m=-5.0)
        fake.conn.mav.distance_sensor_send(fake.boot_ms(), 20, 4000, 65000, 0, 0, 25, 0)  # 650 m, max 40 m

    fake, decisions, _ = run_against(assets, tmp_path, healthy_then(bad), 6.5, "--hold", "1.5")
    good = assert_healthy_phase_sent(fake)
    ref = np.mean([[t.x, t.y, t.z] for t in good[-5:]], axis=0)
    for t in fake.targets_between(SWITCH_S, 1e9):
        assert np.allclose([t.x, t.y, t.z], ref, atol=0.3), "only the committed spot may be sent"
    assert fake.targets_between(SWITCH_S + 1.5 + GRACE_S, 1e9) == []   # dropped after --hold
    assert any("spot dropped" in text for text in fake.texts())
    reasons = {d["reason"].split(":")[0] + ":" + d["reason"].split(":")[1] for d in decisions if not d["valid"]}
    assert any(r.startswith("held: no metric scale") for r in reasons)
    assert not any(d["scale"] and d["scale"] > 10 for d in decisions)


def test_rangefinder_beyond_its_maximum_falls_back_to_relative_altitude(assets, tmp_path):
    def bad(fake: FakeAutopilot, t: float) -> None:
        fake.healthy()
        fake.conn.mav.distance_sensor_send(fake.boot_ms(), 20, 4000, 65000, 0, 0, 25, 0)

    fake, _, _ = run_against(assets, tmp_path, healthy_then(bad))
    assert_healthy_phase_sent(fake)
    late = fake.targets_between(SWITCH_S + GRACE_S, 1e9)
    assert len(late) >= 5 and all(t.z == pytest.approx(AGL_M, abs=0.3) for t in late)


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4"])
def test_committed_spot_is_re_expressed_from_fresh_telemetry_while_out_of_evidence(assets, tmp_path, autopilot):
    """Phase 2: the vehicle flies 2 m north (0.5 s at 4 m/s, with LOCAL_POSITION_NED's velocity: the same step
    without it is an EKF reset, tests/test_position_jumps.py) and fusion has no new evidence (no height above
    ground): the committed spot keeps going out, re-expressed in the new body frame (ArduPilot) or as the same
    local NED point (PX4); phase 3: the autopilot goes silent and the spot is dropped."""
    def script(fake: FakeAutopilot, t: float) -> None:
        if t < SWITCH_S:
            fake.healthy()
        elif t < SWITCH_S + 1.5:
            moving = t < SWITCH_S + 0.5
            north = 5.0 + 4.0 * (t - SWITCH_S) if moving else 7.0
            fake.healthy(ned=(north, -3.0, -10.0), rel_alt_m=-1.0, vel=(4.0 if moving else 0.0, 0.0, 0.0))

    fake, decisions, _ = run_against(assets, tmp_path, script, 6.0, "--autopilot", autopilot)
    good = fake.targets_between(0.0, SWITCH_S)
    assert len(good) >= 5
    ref = np.mean([[t.x, t.y, t.z] for t in good[-5:]], axis=0)
    held = fake.targets_between(SWITCH_S + 0.5, SWITCH_S + 1.4)
    assert len(held) >= 3, "the committed spot must be re-sent at the frame rate"
    shift = np.array([2.0, 0.0, 0.0]) if autopilot == "ardupilot" else np.zeros(3)
    for t in held:
        assert np.allclose([t.x, t.y, t.z], ref - shift, atol=0.3)
    assert fake.targets_between(SWITCH_S + 1.5 + GRACE_S, 1e9) == []
    assert any("spot dropped" in text for text in fake.texts())
    assert any(d["reason"].startswith("held: committed spot") and d["sent"] for d in decisions)


def test_tcp_peer_that_freezes_gets_no_target_captured_after_its_last_telemetry(assets, tmp_path):
    def script(fake: FakeAutopilot, t: float) -> None:
        fake.read = not SWITCH_S <= t < SWITCH_S + 2.0
        if fake.read:
            fake.healthy()

    fake, decisions, _ = run_against(assets, tmp_path, script, 7.0, tcp=True)
    assert len(fake.targets_between(0.0, SWITCH_S)) >= 5
    assert len(fake.targets_between(SWITCH_S + 3.0, 1e9)) >= 5, "sending resumes when the peer is back"
    assert fake.heard_s is not None
    # Capture times are on edge-run's monotonic clock, which is this process's: compare directly.
    frozen_at = fake.heard_s + SWITCH_S
    late = [t for t in fake.targets_between(SWITCH_S, 1e9) if frozen_at + GRACE_S < t.time_usec / 1e6 < frozen_at + 2.0]
    assert late == [], "no target captured more than 1 s after the last telemetry may be sent"
    assert not [d for d in decisions if d["sent"] and frozen_at + GRACE_S < d["capture_time_s"] < frozen_at + 2.0]
