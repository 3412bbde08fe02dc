"""Between frames slower than ArduPilot's estimator needs (updates < 0.5 s apart), edge-run re-sends the newest
frame's sent target at the newest pose (runtime/pipeline/bridge.py). The camera is real edge-run reading a
video whose reads are slowed to FRAME_S each (a slow model or camera); the autopilot is the fake one (a test
double), real pymavlink on both ends over loopback."""
from __future__ import annotations

import json
import time

import numpy as np
import pytest

from edge_landing.cli.run import config_from_args, main
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import Target
from edge_landing.runtime.io.sources import VideoReader
from edge_landing.runtime.pipeline.bridge import TargetBridge
from tests.fake_autopilot import FakeAutopilot
from tests.run_helpers import flat_assets, free_udp_port

AGL_M = 10.0
FRAME_S = 0.6             # one frame every 0.6 s: more than ArduPilot's 0.5 s
SPEED_MS = 0.5            # the vehicle flies north at this speed, so a newer pose gives another body vector


def _target(ned=(9.0, -3.0, 0.0), valid=True) -> Target:
    return Target(1, 10.0, valid, position_body_frd_m=np.array([4.0, 0.0, 10.0]),
                  position_ned_m=None if ned is None else np.array(ned), clearance_m=3.0)


def test_the_bridge_keeps_only_a_sent_target_it_can_re_express_and_waits_its_period():
    bridge = TargetBridge(0.25)
    bridge.decided(_target(), None, sent=True, now_s=10.0)
    assert bridge.due(10.125) is None                     # sent an eighth of a second ago
    due = bridge.due(10.25)
    assert due is not None and due[0].frame_id == 1
    bridge.resent_at(10.25)
    assert bridge.due(10.375) is None and bridge.due(10.5) is not None and bridge.resent == 1
    bridge.decided(_target(), None, sent=False, now_s=10.5)   # the next frame sent nothing: nothing to bridge
    assert bridge.due(11.0) is None
    bridge.decided(_target(ned=None), None, sent=True, now_s=11.0)   # no local position: cannot be re-expressed
    assert bridge.due(12.0) is None
    off = TargetBridge(0.0)
    off.decided(_target(), None, sent=True, now_s=10.0)
    assert not off.enabled and off.due(20.0) is None


@pytest.mark.parametrize("value", ["0.5", "0.01", "-1", "nan"])
def test_a_bridge_period_that_cannot_keep_the_stream_under_half_a_second_is_refused(value):
    with pytest.raises(InputError, match="--bridge"):
        config_from_args(["--bridge", value])


@pytest.fixture(scope="module")
def assets(tmp_path_factory):
    return flat_assets(tmp_path_factory.mktemp("bridge"), AGL_M)


def north_at(t_s: float) -> float:
    return 5.0 + SPEED_MS * t_s


def fly_slowly(assets, tmp_path, monkeypatch, *extra: str, stall=(1e9, 0.0), duration_s: float = 6.0):
    """edge-run on the video at one frame per FRAME_S (and one read that takes ``stall[1]`` s from script time
    ``stall[0]``), the vehicle flying north; returns ([(script time, arrival monotonic time, LANDING_TARGET)],
    the script's start on the monotonic clock)."""
    read = VideoReader.read
    started = [0.0]
    stalled = [False]

    def slow_read(self):
        if not stalled[0] and time.monotonic() - started[0] >= stall[0]:
            stalled[0] = True
            time.sleep(stall[1])
        time.sleep(FRAME_S)
        return read(self)

    monkeypatch.setattr(VideoReader, "read", slow_read)

    def script(fake: FakeAutopilot, t: float) -> None:
        fake.healthy(ned=(north_at(t), -3.0, -AGL_M))

    port = free_udp_port()
    with FakeAutopilot(port, script) as fake:
        started[0] = time.monotonic()
        assert main(["--camera", assets["video"], "--model", assets["model"], "--loop", "--duration", str(duration_s),
                     "--mav", f"udpout:127.0.0.1:{port}", "--allow-unconfirmed", *extra]) == 0
        heard = fake.heard_s
        got = [(t - heard, t, m) for t, m in fake.of_type("LANDING_TARGET")]
    return got, heard


def test_frames_slower_than_the_autopilot_needs_still_give_it_a_target_every_fifth_of_a_second(
        assets, tmp_path, monkeypatch, capsys):
    got, heard = fly_slowly(assets, tmp_path, monkeypatch)
    out = capsys.readouterr().out
    assert len(got) >= 10, out
    gaps = np.diff([t for t, _, _ in got])
    assert gaps.max() < 0.4, gaps                       # frames came 0.6 s apart; ArduPilot needs < 0.5 s
    # ArduPilot counts a message only when its time_usec millisecond differs from the last one's: a re-send that
    # kept its frame's stamp would feed its estimator nothing. Every message here is a new measurement.
    stamps_ms = [m.time_usec // 1000 for _, _, m in got]
    assert all(a != b for a, b in zip(stamps_ms, stamps_ms[1:])), stamps_ms
    # Each vector holds at its stamp (the pose it was expressed at): body x + the vehicle's north then is the
    # spot's north (level, facing north), the same for a frame's target and for its re-sends.
    spot_north = np.array([m.x + north_at(m.time_usec / 1e6 - heard) for _, _, m in got])
    spots = np.split(spot_north, np.flatnonzero(np.abs(np.diff(spot_north)) > 0.5) + 1)
    assert all(np.ptp(run) < 0.15 for run in spots), spot_north
    assert max(len(run) for run in spots) >= 4          # one spot kept across frames and re-sends
    assert np.ptp([m.x for _, _, m in got]) > 0.05      # and the vector did change: re-expressed, not copied
    sent = int(out.split("LANDING_TARGET sent ")[1].split(" ")[0])
    resent = int(out.split("(+")[1].split(" between frames")[0])
    assert resent > 0 and sent + resent == len(got), out


def test_a_stalled_camera_is_bridged_only_until_its_last_target_is_a_second_old(assets, tmp_path, monkeypatch):
    log = tmp_path / "decisions.jsonl"
    got, _ = fly_slowly(assets, tmp_path, monkeypatch, "--log", str(log), stall=(3.0, 2.5), duration_s=7.5)
    arrivals = np.array([arrival for _, arrival, _ in got])
    gaps = np.diff(arrivals)
    assert len(got) >= 8 and gaps.max() > 1.5, gaps      # the stall shows as a gap: nothing made up to fill it
    before_gap = arrivals[int(np.argmax(gaps))]
    captures = [r["capture_time_s"] for r in map(json.loads, log.read_text().splitlines()) if r.get("sent")]
    last_capture = max(c for c in captures if c <= before_gap)
    # LinkConfig.max_target_age_s (what the autopilot accepts), judged on the capture time, not the stamp.
    assert 0.6 < before_gap - last_capture <= 1.05, (before_gap, last_capture)
def test_without_the_bridge_the_stream_has_the_frames_gaps(assets, tmp_path, monkeypatch, capsys):
    got, _ = fly_slowly(assets, tmp_path, monkeypatch, "--bridge", "0", duration_s=4.5)
    gaps = np.diff([t for t, _, _ in got])
    assert len(got) >= 4 and gaps.min() > 0.5, gaps
    assert "(+0 between frames" in capsys.readouterr().out
