"""edge-run --tlog: a recorded video replayed with the MAVLink telemetry log of the same flight.

The logs are real .tlog files (8-byte big-endian arrival time in µs, then the packet), written with pymavlink
and read back through pymavlink's own log reader; the telemetry then passes the live link's checks."""
from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest

from edge_landing.cli.run import main
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.io.mavlink_conn import load_mavutil
from edge_landing.runtime.io.poses import Pose
from edge_landing.runtime.io.telemetry import TelemetryBuffer
from edge_landing.runtime.io.tlog import TlogConfig, TlogTelemetry, parse_video_start
from edge_landing.sim.tlog_writer import LOG_START_UNIX_S, PREROLL_S, write_flight_tlog
from tests.fake_autopilot import FakeAutopilot
from tests.run_helpers import flat_assets, free_udp_port, read_decisions
from tests.test_gimbal import quat

LOCAL_VIDEO_START_S = 1000.0     # where the tests put the video's first frame on the local clock


def level_flight(frames: int = 10) -> list[Pose]:
    """10 m above level ground, flying north at 10 m/s (one metre per frame at 10 frames/s), yaw 0."""
    return [Pose(k, k / 10, (100.0 + k, 50.0, -10.0), 0.0, 0.0, 0.0, 10.0) for k in range(frames)]


@pytest.fixture(scope="module")
def assets(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tlog")
    out = flat_assets(folder, 10.0, frames=10)
    out["tlog"] = str(folder / "flight.tlog")
    write_flight_tlog(Path(out["tlog"]), level_flight(), seed=3)
    rows = ["frame,t,north,east,down,roll,pitch,yaw,agl"]
    rows += [f"{p.frame},{p.t_s},{p.ned_m[0]},{p.ned_m[1]},{p.ned_m[2]},0,0,0,10" for p in level_flight()]
    out["poses"] = str(folder / "poses.csv")
    Path(out["poses"]).write_text("\n".join(rows) + "\n")
    return out


def write_tlog(path: Path, packets: list) -> Path:
    """``packets``: (arrival UNIX s, MAVLink message, (system, component)) in any order."""
    m = load_mavutil().mavlink
    senders: dict = {}
    with open(path, "wb") as fh:
        for t, msg, sender in sorted(packets, key=lambda p: p[0]):
            mav = senders.setdefault(sender, m.MAVLink(None, srcSystem=sender[0], srcComponent=sender[1]))
            fh.write(struct.pack(">Q", int(round(t * 1e6))) + msg.pack(mav))
            mav.seq = (mav.seq + 1) % 256
    return path


def hand_made_log(path: Path, ekf_flags: int, end_s: float = 3.0, pitch_rad: float = 0.0,
                  gimbal_pitch_deg: float | None = None, agl_m: float = 10.0, position: bool = True) -> Path:
    """An ArduPilot-like autopilot at 20 Hz for ``end_s`` seconds from LOG_START_UNIX_S, hovering ``agl_m`` up,
    pitched ``pitch_rad``; with ``gimbal_pitch_deg`` it also reports the gimbal it drives (that far below the
    horizon); without ``position`` it sends no LOCAL_POSITION_NED (no GPS)."""
    m = load_mavutil().mavlink
    ap = (1, 1)
    tilt = 1.0 / np.cos(pitch_rad)
    packets = []
    for j in range(int(end_s * 20) + 1):
        t = j / 20
        ms = int(5000 + 1000 * t)
        arrival = LOG_START_UNIX_S + t + 0.01
        if j % 20 == 0:
            packets.append((arrival, m.MAVLink_heartbeat_message(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                                 0, 0, m.MAV_STATE_ACTIVE, 3), ap))
        packets.append((arrival, m.MAVLink_attitude_message(ms, 0.0, pitch_rad, 0.0, 0.0, 0.0, 0.0), ap))
        if position:
            packets.append((arrival, m.MAVLink_local_position_ned_message(ms, 0.0, 0.0, -agl_m, 0.0, 0.0, 0.0), ap))
        packets.append((arrival, m.MAVLink_distance_sensor_message(ms, 20, 13000, round(100 * agl_m * tilt), 0, 0, 25,
                                                                   0), ap))
        if gimbal_pitch_deg is not None:
            packets.append((arrival, m.MAVLink_gimbal_device_attitude_status_message(
                0, 0, ms, m.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME, quat(0.0, gimbal_pitch_deg, 0.0),
                math.nan, math.nan, math.nan, 0, math.nan, math.nan, 0), ap))
        if j % 10 == 0:
            packets.append((arrival, m.MAVLink_ekf_status_report_message(ekf_flags, 0.1, 0.1, 0.1, 0.1, 0.0), ap))
    return write_tlog(path, packets)


def test_the_video_start_is_read_in_each_form_and_refused_in_one_line_otherwise():
    first = LOG_START_UNIX_S
    assert parse_video_start("+2.5", first) == pytest.approx(first + 2.5)
    assert parse_video_start("1767225602.25", first) == pytest.approx(1767225602.25)
    assert parse_video_start("2026-01-01T00:00:02Z", first) == pytest.approx(first + 2.0)
    assert parse_video_start("2026-01-01T01:00:02+01:00", first) == pytest.approx(first + 2.0)
    for bad, said in (("yesterday", "is not a time"), ("2026-01-01T00:00:02", "no time zone"),
                      ("1000", "between 2000 and 2100"), ("+nan", "between 2000 and 2100")):
        with pytest.raises(InputError, match=said):
            parse_video_start(bad, first)


def test_the_log_feeds_the_telemetry_buffer_on_the_frames_clock(assets):
    log = TlogTelemetry(TlogConfig(assets["tlog"], f"+{PREROLL_S}"))
    buf = TelemetryBuffer()
    offset = LOCAL_VIDEO_START_S - log.video_start_unix_s
    frame_s = 0.55                                   # between frames 5 and 6: north 105.5 m
    log.feed_until(buf, log.video_start_unix_s + frame_s + 0.1, offset)
    match = buf.lookup(LOCAL_VIDEO_START_S + frame_s, LOCAL_VIDEO_START_S + frame_s + 0.05)
    assert match.fresh and match.state is not None, match.reason
    # One-way time stamps: the link's 12 ms latency is taken into the clock offset (0.12 m at 10 m/s).
    np.testing.assert_allclose(match.state.position_ned_m, [105.5, 50.0, -10.0], atol=0.2)
    assert match.state.agl_m == pytest.approx(10.0, abs=0.01) and match.state.agl_source == "rangefinder"
    assert log.peer == (1, 1)
    # The ground station's heartbeat opens the log (before the autopilot is known), later ones are other senders'.
    assert log.counts["before_autopilot"] == 1 and log.counts["other_senders"] >= 1
    # A frame half a second past what was fed: no sample within the match window, and the newest is stale.
    assert not buf.lookup(LOCAL_VIDEO_START_S + 1.2, LOCAL_VIDEO_START_S + 1.25).fresh
    log.close()


def test_the_logs_estimator_status_and_its_gaps_are_trusted_as_the_links_are(tmp_path):
    m = load_mavutil().mavlink
    healthy = m.EKF_ATTITUDE | m.EKF_VELOCITY_HORIZ | m.EKF_POS_HORIZ_REL | m.EKF_POS_HORIZ_ABS | m.EKF_PRED_POS_HORIZ_REL
    for flags, said in ((healthy, ""), (0, "attitude not usable")):
        log = TlogTelemetry(TlogConfig(str(hand_made_log(tmp_path / f"ekf{flags}.tlog", flags)), "+1"))
        buf = TelemetryBuffer()
        offset = LOCAL_VIDEO_START_S - log.video_start_unix_s
        log.feed_until(buf, log.video_start_unix_s + 0.6, offset)
        match = buf.lookup(LOCAL_VIDEO_START_S + 0.5, LOCAL_VIDEO_START_S + 0.55)
        assert match.fresh == (not said) and said in match.reason
        if not said:   # the log ends 3 s after it starts: a frame 1.5 s later finds its telemetry stale
            log.feed_until(buf, log.video_start_unix_s + 3.6, offset)
            late = buf.lookup(LOCAL_VIDEO_START_S + 3.5, LOCAL_VIDEO_START_S + 3.55)
            assert not late.fresh and "stale" in late.reason and log.ended
        log.close()


def test_edge_run_replays_a_video_with_its_tlog_as_it_replays_its_poses(assets, tmp_path):
    """The same flight through --poses and through --tlog: the same targets, each placed on the ground."""
    logs = {}
    for how, extra in (("poses", ["--poses", assets["poses"]]),
                       ("tlog", ["--tlog", assets["tlog"], "--tlog-video-start", f"+{PREROLL_S}"])):
        logs[how] = tmp_path / f"{how}.jsonl"
        assert main(["--camera", assets["video"], "--model", assets["model"], *extra, "--vehicle-radius", "0.5",
                     "--margin", "0.5", "--log", str(logs[how]), "--allow-unconfirmed"]) == 0
    header = json.loads(logs["tlog"].read_text().splitlines()[0])["run"]
    assert header["tlog"] == assets["tlog"] and header["poses"] is None
    by_poses, by_tlog = read_decisions(logs["poses"]), read_decisions(logs["tlog"])
    assert len(by_tlog) == 10 and all(d["valid"] and d["telemetry"] for d in by_tlog)
    for p, t in zip(by_poses, by_tlog):
        assert abs(t["ned_m"][2]) < 0.3                        # on the ground (down = 0 in local NED)
        np.testing.assert_allclose(t["ned_m"], p["ned_m"], atol=0.25)
        assert t["scale_source"].startswith("altitude") and t["agl_m"] == pytest.approx(10.0, abs=0.05)


def test_a_gimbal_in_the_log_places_the_camera(assets, tmp_path):
    """The vehicle hovers 11.5° nose down while its gimbal holds the camera 45° below the horizon (the flat-ground
    model's view): read from the log, the gimbal's reports put every spot on the ground; the fixed mount does not."""
    m = load_mavutil().mavlink
    tlog = hand_made_log(tmp_path / "gimbal.tlog", m.EKF_ATTITUDE | m.EKF_POS_HORIZ_REL, pitch_rad=-0.2,
                         gimbal_pitch_deg=-45.0)
    downs = {}
    for extra in ([], ["--gimbal", "mavlink"]):
        log_path = tmp_path / f"g{len(extra)}.jsonl"
        assert main(["--camera", assets["video"], "--model", assets["model"], "--tlog", str(tlog),
                     "--tlog-video-start", "+1", "--log", str(log_path), "--allow-unconfirmed", *extra]) == 0
        decisions = read_decisions(log_path)
        assert len(decisions) == 10 and all(d["valid"] for d in decisions), [d["reason"] for d in decisions]
        downs[bool(extra)] = [d["ned_m"][2] for d in decisions]
        if extra:
            assert all(d["gimbal_mount_deg"][1] == pytest.approx(-45.0 + math.degrees(0.2), abs=0.5)
                       for d in decisions)
    assert max(abs(v) for v in downs[True]) < 0.1          # on the ground, 10 m below the vehicle
    assert min(abs(v) for v in downs[False]) > 0.3          # the body-fixed mount is off by the vehicle's tilt


@pytest.mark.parametrize("argv, expected", [
    (["--tlog", "{d}/missing.tlog", "--tlog-video-start", "+1"], "does not exist"),
    (["--tlog", "{poses}", "--tlog-video-start", "+1"], "not a .tlog"),
    (["--tlog", "{d}/flight.bin", "--tlog-video-start", "+1"], "dataflash"),
    (["--tlog", "{tlog}"], "needs --tlog-video-start"),
    (["--tlog-video-start", "+1"], "needs --tlog"),
    (["--tlog", "{tlog}", "--tlog-video-start", "yesterday"], "is not a time"),
    (["--tlog", "{tlog}", "--tlog-video-start", "2026-01-01T00:00:02"], "no time zone"),
    (["--tlog", "{tlog}", "--tlog-video-start", "+1", "--poses", "{poses}"], "not both"),
    (["--tlog", "{tlog}", "--tlog-video-start", "+1", "--loop"], "--loop with --tlog"),
])
def test_tlog_mistakes_are_one_line(assets, capsys, argv, expected):
    Path(assets["dir"], "flight.bin").write_bytes(b"\xa3\x95\x80" * 40)
    argv = [a.format(d=assets["dir"], tlog=assets["tlog"], poses=assets["poses"]) for a in argv]
    assert main(["--camera", assets["video"], "--model", assets["model"], *argv]) == 2
    err = capsys.readouterr().err
    assert expected in err and len(err.strip().splitlines()) == 1, err


def test_a_tlog_needs_a_recording(assets, capsys):
    assert main(["--camera", "sim", "--tlog", assets["tlog"], "--tlog-video-start", "+1"]) == 2
    assert "is not a recording" in capsys.readouterr().err


def test_the_sims_tlog_streams_what_an_autopilot_would(assets):
    """20 Hz pose messages on the autopilot's own boot clock, a 2 Hz estimator status, 1 Hz heartbeats."""
    conn = load_mavutil().mavlink_connection(assets["tlog"], notimestamps=False)
    kinds: dict = {}
    boot_ms, arrivals = [], []
    while (msg := conn.recv_msg()) is not None:
        kinds[(msg.get_type(), msg.get_srcSystem())] = kinds.get((msg.get_type(), msg.get_srcSystem()), 0) + 1
        arrivals.append(msg._timestamp)
        if msg.get_type() == "ATTITUDE":
            boot_ms.append(msg.time_boot_ms)
    conn.close()
    span_s = PREROLL_S + 0.9                                      # the pre-roll and ten frames at 10 frames/s
    assert kinds[("ATTITUDE", 1)] == kinds[("LOCAL_POSITION_NED", 1)] == int(round(span_s * 20)) + 1
    assert kinds[("EKF_STATUS_REPORT", 1)] == int(span_s * 2) + 1 and kinds[("HEARTBEAT", 255)] >= 2
    assert np.all(np.diff(boot_ms) == 50) and arrivals[0] == LOG_START_UNIX_S and np.all(np.diff(arrivals) >= 0)


def test_a_log_whose_clock_went_back_is_said_once_and_still_read(tmp_path, caplog):
    """A ground station's wall clock stepped back 30 s in flight: said once; the packets after it are still read."""
    m = load_mavutil().mavlink
    mav = m.MAVLink(None, srcSystem=1, srcComponent=1)
    path = tmp_path / "stepped.tlog"
    with open(path, "wb") as fh:
        for j in range(40):
            t = LOG_START_UNIX_S + j / 20 - (30.0 if j >= 20 else 0.0)
            msgs = [m.MAVLink_heartbeat_message(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3),
                    m.MAVLink_attitude_message(1000 + 50 * j, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)]
            for msg in msgs:
                fh.write(struct.pack(">Q", int(t * 1e6)) + msg.pack(mav))
                mav.seq = (mav.seq + 1) % 256
    log = TlogTelemetry(TlogConfig(str(path), "+0"))
    with caplog.at_level("WARNING"):
        log.feed_until(TelemetryBuffer(), LOG_START_UNIX_S + 5.0, 0.0)
    said = [r.getMessage() for r in caplog.records if "clock went back" in r.getMessage()]
    assert len(said) == 1 and "went back 29.9" in said[0]          # 0.95 s after the start to 29 s before it
    assert log.counts["packets"] == 80 and log.ended
    log.close()


@pytest.mark.parametrize("armed", [False, True])
def test_targets_made_from_replayed_poses_never_reach_an_armed_autopilot(assets, tmp_path, armed):
    """A replay (--poses, --tlog, the sim camera) places targets with another flight's poses: an autopilot that is
    flying must not get them. The autopilot is a TEST DOUBLE (tests.fake_autopilot); the disarmed run is the
    control that shows targets do reach it otherwise."""
    m = load_mavutil().mavlink
    base_mode = m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (m.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)

    def script(fake: FakeAutopilot, t: float) -> None:
        fake.conn.mav.heartbeat_send(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, base_mode, 0,
                                     m.MAV_STATE_ACTIVE)

    port, log_path = free_udp_port(), tmp_path / "decisions.jsonl"
    with FakeAutopilot(port, script) as fake:
        assert main(["--camera", assets["video"], "--model", assets["model"], "--poses", assets["poses"], "--loop",
                     "--duration", "2.5", "--mav", f"udpout:127.0.0.1:{port}", "--log", str(log_path),
                     "--vehicle-radius", "0.5", "--margin", "0.5", "--allow-unconfirmed"]) == 0
    targets, decisions = fake.of_type("LANDING_TARGET"), read_decisions(log_path)
    held = [d for d in decisions if d["not_sent_because"].startswith("held: the autopilot is armed")]
    if not armed:
        assert len(targets) >= 5 and not held
        return
    assert targets == [] and len(held) >= 5
    assert "--poses replay" in held[0]["not_sent_because"]
    assert any("replay targets held" in text for text in fake.texts())
