"""edge-run --flight-record: a flight kept as it happened (frames, their capture times, the link's packets) and
replayed on the desk with --tlog, against a test double autopilot (real pymavlink, loopback UDP)."""
from __future__ import annotations

import csv
import json

import cv2
import numpy as np
import pytest

from edge_landing.cli.run import main
from edge_landing.runtime.io.flight_record import TLOG_NAME, VIDEO_NAME
from edge_landing.runtime.io.mavlink_conn import load_mavutil
from tests.fake_autopilot import FakeAutopilot
from tests.run_helpers import flat_assets, free_udp_port, read_decisions

SPEED_MPS = 2.0     # the vehicle flies north, 10 m above level ground: a frame timed wrongly lands elsewhere


@pytest.fixture(scope="module")
def assets(tmp_path_factory):
    return flat_assets(tmp_path_factory.mktemp("record"), 10.0)


def flying_north(fake: FakeAutopilot, t: float) -> None:
    fake.healthy(ned=(5.0 + SPEED_MPS * t, -3.0, -10.0))


def test_a_recorded_flight_replays_to_the_same_targets(assets, tmp_path):
    folder, live_log, replay_log = tmp_path / "flight", tmp_path / "live.jsonl", tmp_path / "replay.jsonl"
    port = free_udp_port()
    with FakeAutopilot(port, flying_north):
        assert main(["--camera", assets["video"], "--model", assets["model"], "--loop", "--duration", "3",
                     "--mav", f"udpout:127.0.0.1:{port}", "--flight-record", str(folder), "--log", str(live_log),
                     "--allow-unconfirmed", "--threads", "1"]) == 0
    with open(folder / "camera.frames.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    cap = cv2.VideoCapture(str(folder / VIDEO_NAME))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == len(rows) >= 10
    live = {d["frame"]: d for d in read_decisions(live_log)}
    assert [int(r["index"]) for r in rows] == list(range(len(rows)))
    assert all(int(r["frame"]) in live for r in rows)          # every recorded frame is one the pipeline took
    # The link's packets, as the link received them: the autopilot's telemetry is there.
    conn = load_mavutil().mavlink_connection(str(folder / TLOG_NAME), notimestamps=False)
    kinds = set()
    while (msg := conn.recv_msg()) is not None:
        kinds.add((msg.get_type(), msg.get_srcSystem()))
    conn.close()
    assert {("ATTITUDE", 1), ("LOCAL_POSITION_NED", 1), ("HEARTBEAT", 1)} <= kinds

    # The replay needs no start time: the recorder wrote each frame's capture time beside the video.
    assert main(["--camera", str(folder / VIDEO_NAME), "--tlog", str(folder / TLOG_NAME), "--model", assets["model"],
                 "--log", str(replay_log), "--allow-unconfirmed", "--threads", "1"]) == 0
    header = json.loads(replay_log.read_text().splitlines()[0])["run"]
    assert header["tlog"] == str(folder / TLOG_NAME)
    replay = read_decisions(replay_log)
    assert len(replay) == len(rows)
    compared = 0
    for row, again in zip(rows, replay):
        before = live[int(row["frame"])]
        if before["valid"] and before["sent"] is not None and again["valid"]:
            np.testing.assert_allclose(again["ned_m"], before["ned_m"], atol=0.1)   # 2 m/s: within 50 ms
            compared += 1
    assert compared >= 0.8 * len(rows), (compared, len(rows))


def test_a_folder_that_holds_a_recording_is_not_written_over(assets, tmp_path, capsys):
    folder = tmp_path / "flight"
    folder.mkdir()
    (folder / VIDEO_NAME).write_bytes(b"an earlier flight")
    assert main(["--camera", assets["video"], "--model", assets["model"], "--flight-record", str(folder)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "already holds a recording" in err[0]
    assert (folder / VIDEO_NAME).read_bytes() == b"an earlier flight"
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert main(["--camera", assets["video"], "--model", assets["model"], "--flight-record", str(afile)]) == 2
    assert "is not a folder" in capsys.readouterr().err


def test_the_recorders_clock_does_not_step_with_the_wall_clock(tmp_path, monkeypatch):
    """The link's packets and the frames share one UNIX offset taken once: a wall clock set in flight (NTP on a
    companion computer without a real-time clock) moves neither."""
    import time

    from edge_landing.runtime.io.flight_record import unix_time
    from edge_landing.runtime.io.tlog import TlogWriter

    before = unix_time(time.monotonic())
    real_time = time.time
    monkeypatch.setattr(time, "time", lambda: real_time() + 3600.0)
    writer = TlogWriter(str(tmp_path / "link.tlog"))
    m = load_mavutil().mavlink
    msg = m.MAVLink_attitude_message(1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    msg.pack(m.MAVLink(None, srcSystem=1, srcComponent=1))
    writer.write(msg)
    writer.close()
    monkeypatch.undo()
    conn = load_mavutil().mavlink_connection(str(tmp_path / "link.tlog"), notimestamps=False)
    stamped = conn.recv_msg()._timestamp
    conn.close()
    assert abs(stamped - before) < 5.0 and abs(unix_time(time.monotonic()) - time.time()) < 5.0
