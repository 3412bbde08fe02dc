"""The MAVLink link with real pymavlink peers on loopback UDP/TCP, and the telemetry buffer."""
from __future__ import annotations

import logging
import math
import socket
import threading
import time
from dataclasses import replace

import numpy as np
import pytest

from edge_landing.cli.run import main
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import Target
from edge_landing.runtime.io.mavlink_link import (
    Autopilot,
    LinkConfig,
    MavlinkLink,
    check_url,
    load_mavutil,
    load_signing_key,
)
from edge_landing.runtime.io.telemetry import TelemetryBuffer
from tests.fake_autopilot import answer_param_request
from tests.run_helpers import (
    LoopbackAutopilot,
    flat_assets,
    flat_ground_model,
    free_tcp_port,
    free_udp_port,
    read_decisions,
    wait_for,
)

AGL_M = 10.0


@pytest.fixture(scope="module")
def assets(tmp_path_factory):
    return flat_assets(tmp_path_factory.mktemp("mav"), AGL_M)


def edge_run(assets, *extra):
    # Random video frames of a flat-ground model: nothing for motion geometry to confirm, so the explicit flag.
    # The video is read as fast as the CPU allows: every frame's target is checked, so no rate cap.
    return main(["--camera", assets["video"], "--model", assets["model"], "--allow-unconfirmed", "--target-hz", "0",
                 *extra])


def test_ardupilot_landing_target_and_heartbeat_decoded_by_a_pymavlink_peer(assets):
    port = free_udp_port()
    # The autopilot sends telemetry: without fresh telemetry no target may leave (ARCHITECTURE.md §12).
    with LoopbackAutopilot(port, telemetry=True) as peer:
        assert edge_run(assets, "--mav", f"udpout:127.0.0.1:{port}") == 0
        wait_for(lambda: len(peer.of_type("LANDING_TARGET")) >= 8, 3.0)
    targets, beats = peer.of_type("LANDING_TARGET"), peer.of_type("HEARTBEAT")
    assert len(targets) == 8 and beats
    m = peer.mavutil.mavlink
    assert m.WIRE_PROTOCOL_VERSION == "2.0"
    for t in targets:
        assert t.frame == 12 and t.position_valid == 1 and t.type == 3 and list(t.q) == [1.0, 0.0, 0.0, 0.0]
        xyz = np.array([t.x, t.y, t.z])
        assert t.distance == pytest.approx(np.linalg.norm(xyz), rel=1e-5) and t.distance > 0
        assert t.x > 0 and t.z == pytest.approx(AGL_M, abs=0.3)  # ahead, on the ground 10 m below
        assert t.size_x > 0 and t.size_y > 0 and abs(t.angle_y) < math.pi / 2
        assert t.get_srcComponent() == 191
    assert all(b.get_type() == "HEARTBEAT" for b in beats)
    b = beats[0]
    assert (b.type, b.autopilot, b.get_srcComponent()) == (m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 191)
    assert any("found" in s.text for s in peer.of_type("STATUSTEXT"))
    times = [t.time_usec for t in targets]
    assert times == sorted(times) and len(set(times)) == len(times)


@pytest.mark.parametrize("yaw_deg, grid", [(0.0, "ned"), (90.0, "ned"), (90.0, "frame")])
def test_px4_local_ned_target_agrees_with_the_autopilot_telemetry(assets, yaw_deg, grid):
    port = free_udp_port()
    pos = (5.0, -3.0, -AGL_M)
    log_path = assets["dir"] / f"px4_{yaw_deg:.0f}_{grid}.jsonl"
    with LoopbackAutopilot(port, telemetry=True, position_ned=pos, yaw_rad=math.radians(yaw_deg), autopilot="px4") as ap:
        # Telemetry flows once the autopilot hears our heartbeat; loop the video for a fixed time.
        assert edge_run(assets, "--loop", "--duration", "2.5", "--mav", f"udpout:127.0.0.1:{port}",
                        "--autopilot", "px4", "--grid", grid, "--log", str(log_path)) == 0
        wait_for(lambda: False, 0.2)
    targets = ap.of_type("LANDING_TARGET")
    assert len(targets) >= 5
    requested = {int(c.param1) for c in ap.of_type("COMMAND_LONG") if c.command == 511}  # SET_MESSAGE_INTERVAL
    # ATTITUDE, GLOBAL_POSITION_INT, DISTANCE_SENSOR, LOCAL_POSITION_NED, EKF_STATUS_REPORT, ESTIMATOR_STATUS
    assert requested == {30, 33, 132, 32, 193, 230}
    for t in targets:
        assert t.frame == 1 and t.position_valid == 1 and t.type == 3
        rel = np.array([t.x - pos[0], t.y - pos[1], t.z - pos[2]])
        assert rel[2] == pytest.approx(AGL_M, abs=0.3)             # on the ground: local down = 0
        heading = math.degrees(math.atan2(rel[1], rel[0]))
        assert abs((heading - yaw_deg + 180) % 360 - 180) < 15     # ahead of the nose, whichever way it points
    decisions = read_decisions(log_path)
    assert any(d["telemetry"] and d["agl_m"] == pytest.approx(AGL_M, abs=0.01) for d in decisions)


def test_px4_without_local_position_sends_nothing_and_says_why(assets):
    port = free_udp_port()
    log_path = assets["dir"] / "px4_none.jsonl"
    with LoopbackAutopilot(port, autopilot="px4") as peer:
        assert edge_run(assets, "--mav", f"udpout:127.0.0.1:{port}", "--autopilot", "px4",
                        "--log", str(log_path)) == 0
        time.sleep(0.2)
    assert not peer.of_type("LANDING_TARGET") and peer.of_type("HEARTBEAT")
    decisions = read_decisions(log_path)
    assert decisions and all("LOCAL_POSITION_NED" in d["not_sent_because"] for d in decisions if d["valid"])


def test_nobody_listening_then_peer_appears_sending_resumes():
    port = free_udp_port()
    link = MavlinkLink(LinkConfig(f"udpout:127.0.0.1:{port}", error_quiet_s=0.3), TelemetryBuffer()).start()
    target = Target(0, time.monotonic(), True, position_body_frd_m=np.array([5.0, 0.0, 10.0]), angle_x_rad=0.0,
                    angle_y_rad=0.3, size_x_rad=0.2, size_y_rad=0.2, clearance_m=3.0)
    try:
        for _ in range(20):
            link.send_target(target, None)
            time.sleep(0.01)
        assert link.counts["send_errors"] > 0 and not link.up    # 'port unreachable' seen, loop not stopped
        with LoopbackAutopilot(port, telemetry=True) as peer:  # "up" means the autopilot is heard
            target = replace(target, capture_time_s=time.monotonic())  # older than 1 s would be dropped
            assert wait_for(lambda: (link.send_target(target, None), bool(peer.of_type("LANDING_TARGET")))[1], 5.0)
            assert wait_for(lambda: link.up, 3.0)
    finally:
        link.stop()


def test_edge_run_survives_a_dead_udp_port_and_a_closed_tcp_port(assets):
    assert edge_run(assets, "--mav", f"udpout:127.0.0.1:{free_udp_port()}") == 0
    assert edge_run(assets, "--mav", f"tcp:127.0.0.1:{free_tcp_port()}") == 0


def test_tcp_reset_reconnects_and_resumes():
    port = free_tcp_port()
    server = socket.socket()
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", port))
    server.listen(2)
    link = MavlinkLink(LinkConfig(f"tcp:127.0.0.1:{port}", reconnect_min_s=0.1, reconnect_max_s=0.2),
                       TelemetryBuffer()).start()
    try:
        first, _ = server.accept()
        first.close()                                   # the peer resets the connection
        server.settimeout(5.0)
        second, _ = server.accept()                     # the link came back on its own
        second.settimeout(3.0)
        data = second.recv(4096)
        mav = load_mavutil().mavlink.MAVLink(None)
        msgs = mav.parse_buffer(data) or []
        assert any(m.get_type() == "HEARTBEAT" for m in msgs)
        assert link.counts["reconnects"] >= 1
        second.close()
    finally:
        link.stop()
        server.close()


def test_signed_messages_with_a_key_file(assets, tmp_path):
    key = bytes(range(32))
    key_file = tmp_path / "mav.key"
    key_file.write_bytes(key)
    port = free_udp_port()
    with LoopbackAutopilot(port, telemetry=True) as peer:
        peer.conn.setup_signing(key, sign_outgoing=True)
        assert edge_run(assets, "--max-frames", "3", "--mav", f"udpout:127.0.0.1:{port}", "--mav-key", str(key_file)) == 0
        wait_for(lambda: len(peer.of_type("LANDING_TARGET")) >= 3, 3.0)
    targets = peer.of_type("LANDING_TARGET")
    assert len(targets) == 3 and all(t._signed for t in targets)
    (tmp_path / "hex.key").write_text(key.hex())
    assert load_signing_key(str(tmp_path / "hex.key")) == key


def test_bad_key_and_bad_url_are_one_line_errors(assets, tmp_path, capsys, caplog):
    (tmp_path / "short.key").write_bytes(b"12345")
    assert edge_run(assets, "--mav", "udpout:127.0.0.1:14550", "--mav-key", str(tmp_path / "short.key")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "expected 32 raw bytes" in err[0]
    for url in ("udpout:nohost", "bluetooth:xx", "/dev/ttyUSB0,fast"):
        with pytest.raises(InputError):
            check_url(url)
    with pytest.raises(InputError, match="port 99999 is not in 1-65535"):
        check_url("udpout:127.0.0.1:99999")
    with pytest.raises(InputError, match="ardupilot, px4"):
        Autopilot.from_string("inav")
    # a bad --mav with the sim camera: the error is the only line (nothing said about telemetry before it)
    caplog.clear()
    with caplog.at_level(logging.INFO):
        assert edge_run(assets, "--camera", "sim", "--mav", "udpout:127.0.0.1:0") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "port 0 is not in 1-65535" in err[0], err
    assert not [r.message for r in caplog.records if "telemetry" in r.message]


def test_telemetry_interpolation_yaw_wrap_window_and_clock_offset():
    buf = TelemetryBuffer()
    # Autopilot clock starts at 100 s; arrivals are 1000 s + remote - 100 plus jitter (min latency 2 ms).
    for i, jitter in zip(range(5), (0.002, 0.010, 0.002, 0.030, 0.002)):
        remote_ms = 100_000 + i * 100
        yaw = math.remainder(math.pi - 0.05 + 0.025 * i, 2 * math.pi)
        buf.add_attitude(0.0, 0.1 * i, yaw, remote_ms, arrival_s=1000.0 + i * 0.1 + jitter)
        buf.add_position(float(i), 0.0, -10.0, remote_ms, arrival_s=1000.0 + i * 0.1 + jitter)
    s = buf.state_at(1000.002 + 0.15)                # halfway between samples 1 and 2
    assert s.attitude.pitch_rad == pytest.approx(0.15, abs=1e-6)
    assert s.position_ned_m[0] == pytest.approx(1.5, abs=1e-6)
    s = buf.state_at(1000.002 + 0.25)                # yaw wraps from +pi to -pi between samples 2 and 3
    expected = math.pi - 0.05 + 0.025 * 2.5
    assert math.cos(s.attitude.yaw_rad - expected) == pytest.approx(1.0, abs=1e-9)
    assert buf.state_at(1000.0 + 0.4 + 1.0) is None  # too far from any sample: no guess
    buf.add_rangefinder(12.0, 100_400, arrival_s=1000.402)
    buf.add_relative_alt(11.0, 100_400, arrival_s=1000.402)
    s = buf.state_at(1000.402)
    assert s.agl_source == "rangefinder" and s.agl_m == pytest.approx(12.0 * math.cos(0.4), rel=1e-6)


def test_link_receives_telemetry_from_an_autopilot():
    port = free_udp_port()
    buf = TelemetryBuffer()
    with LoopbackAutopilot(port, telemetry=True, position_ned=(1.0, 2.0, -30.0)):
        link = MavlinkLink(LinkConfig(f"udpout:127.0.0.1:{port}"), buf).start()
        try:
            assert wait_for(lambda: buf.state_at(time.monotonic()) is not None
                            and buf.state_at(time.monotonic()).position_ned_m is not None, 5.0)
            s = buf.state_at(time.monotonic())
            assert list(s.position_ned_m) == [1.0, 2.0, -30.0] and s.agl_m == pytest.approx(30.0)
            assert link.peer == (1, 1)
        finally:
            link.stop()


def test_udpin_link_answers_a_ground_station_that_connects(assets):
    port = free_udp_port()
    mavutil = load_mavutil()
    gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    got, stop = [], threading.Event()

    def ground_station():
        t0 = time.monotonic()
        while not stop.is_set():
            # An autopilot that connects to edge-run's udpin port (quadrotor, ArduPilot) with its telemetry.
            boot_ms = int((time.monotonic() - t0) * 1000) + 1
            gcs.mav.heartbeat_send(2, 3, 0, 0, 0)
            gcs.mav.attitude_send(boot_ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            gcs.mav.global_position_int_send(boot_ms, 0, 0, 0, int(AGL_M * 1000), 0, 0, 0, 0)
            msg = gcs.recv_match(blocking=True, timeout=0.05)
            if msg is not None:
                got.append(msg)
                answer_param_request(gcs.mav, msg)     # its precision-landing setup, as ArduPilot answers

    thread = threading.Thread(target=ground_station, daemon=True)
    thread.start()
    try:
        assert edge_run(assets, "--loop", "--duration", "1.5", "--mav", f"udpin:127.0.0.1:{port}") == 0
    finally:
        stop.set()
        thread.join(timeout=3)
        gcs.close()
    kinds = {m.get_type() for m in got}
    assert {"HEARTBEAT", "LANDING_TARGET"} <= kinds


@pytest.mark.slow
def test_sim_flight_video_to_landing_targets(assets, tmp_path):
    sim = pytest.importorskip("edge_landing.sim")
    sim.generate(sim.SimConfig(out=tmp_path / "flight", frames=6, width=128, height=96, flight=True))
    video = tmp_path / "flight" / "flight.mp4"
    port = free_udp_port()
    log_path = tmp_path / "t.jsonl"
    # The peer plays the autopilot's telemetry: with --mav, no target is sent without it (§12 fresh telemetry).
    with LoopbackAutopilot(port, telemetry=True, position_ned=(0.0, 0.0, -AGL_M)) as peer:
        assert main(["--camera", str(video), "--model", assets["model"], "--mav", f"udpout:127.0.0.1:{port}",
                     "--log", str(log_path), "--allow-unconfirmed", "--target-hz", "0"]) == 0   # every frame's
        wait_for(lambda: len(peer.of_type("LANDING_TARGET")) >= 6, 3.0)
    decisions = read_decisions(log_path)
    assert len(decisions) == 6
    targets = peer.of_type("LANDING_TARGET")
    assert len(targets) == sum(d["sent"] for d in decisions) == 6
    assert all(t.frame == 12 and t.position_valid == 1 and t.x > 0 and t.z > 0 for t in targets)


def test_in_flight_altitude_scale_from_autopilot_telemetry(assets, tmp_path):
    half = flat_ground_model(tmp_path / "half.onnx", agl_m=AGL_M / 2)  # a model that sees everything 2x too close
    port = free_udp_port()
    log_path = tmp_path / "alt.jsonl"
    with LoopbackAutopilot(port, telemetry=True, position_ned=(0.0, 0.0, -AGL_M)) as ap:
        assert main(["--camera", assets["video"], "--loop", "--duration", "2.5", "--model", str(half),
                     "--mav", f"udpout:127.0.0.1:{port}", "--log", str(log_path), "--allow-unconfirmed"]) == 0
    decisions = read_decisions(log_path)
    scaled = [d for d in decisions if d["scale_source"].startswith("altitude")]
    assert scaled and all(d["scale"] == pytest.approx(2.0, rel=0.02) for d in scaled)
    late = [t for t in ap.of_type("LANDING_TARGET")][-3:]
    assert late and all(t.z == pytest.approx(AGL_M, abs=0.3) for t in late)


@pytest.mark.parametrize("field, value", [("system_id", 999), ("component_id", 0), ("target_system", 300)])
def test_link_ids_beyond_one_byte_are_refused(field, value):
    """MAVLink packs ids in one byte: 999 used to kill the link thread at its first heartbeat."""
    from edge_landing.runtime.core.errors import InputError

    with pytest.raises(InputError, match="between 1 and 255"):
        LinkConfig("udpout:127.0.0.1:9", **{field: value})
