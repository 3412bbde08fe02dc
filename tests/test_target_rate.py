"""LANDING_TARGET at most --target-hz on average (io.send_rate): a video file read as fast as the CPU allows
must not flood the autopilot's link. Real MAVLink over loopback, decoded by pymavlink in the fake autopilot
(a test double)."""
from __future__ import annotations

import time

import numpy as np
import pytest

from edge_landing.cli.run import main
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import Target
from edge_landing.runtime.io.mavlink_link import LinkConfig, MavlinkLink
from edge_landing.runtime.io.send_rate import SendRate
from edge_landing.runtime.io.telemetry import TelemetryBuffer
from tests.fake_autopilot import FakeAutopilot
from tests.run_helpers import (
    LoopbackAutopilot,
    flat_assets,
    free_udp_port,
    read_decisions,
    wait_for,
    wait_until_sendable,
)

AGL_M = 10.0


def _sent(rate: SendRate, fps: float, seconds: float) -> int:
    return sum(rate.allow(k / fps) for k in range(int(round(fps * seconds))))


def test_the_cap_holds_on_average_and_a_camera_under_it_is_untouched():
    assert _sent(SendRate(20.0), 500.0, 10.0) in range(199, 203)      # a video read at 500 frames/s
    assert _sent(SendRate(20.0), 25.0, 10.0) in range(199, 203)       # just above the cap: at the cap, not 12.5
    assert _sent(SendRate(20.0), 10.0, 10.0) == 100                   # under it: every frame
    assert _sent(SendRate(0.0), 500.0, 1.0) == 500                    # 0: no cap
    rate = SendRate(20.0)
    assert rate.allow(0.0) and not rate.allow(0.001)                   # no burst from a standing start
    assert rate.allow(1.0) and rate.allow(1.001) and not rate.allow(1.002)   # after a pause: two at most


@pytest.mark.parametrize("hz", [1.0, -5.0, 2000.0, float("nan")])
def test_a_bad_cap_is_refused(hz):
    with pytest.raises(InputError, match="rate cap"):
        LinkConfig("udpout:127.0.0.1:9", max_target_hz=hz)


def test_targets_offered_back_to_back_leave_at_the_cap_and_say_why_not():
    port = free_udp_port()
    with FakeAutopilot(port, lambda f, t: f.healthy()) as fake:
        link = MavlinkLink(LinkConfig(f"udpout:127.0.0.1:{port}", max_target_hz=20.0), TelemetryBuffer()).start()
        try:
            assert wait_until_sendable(link)
            body = np.array([5.0, 0.0, 10.0])
            start, results = time.monotonic(), []
            while time.monotonic() - start < 1.0:
                target = Target(len(results), time.monotonic(), True, position_body_frd_m=body, clearance_m=3.0)
                results.append(link.send_target(target, None))
                time.sleep(0.002)
            sent = sum(ok for ok, _ in results)
            assert 19 <= sent <= 23 and len(results) > 100, (sent, len(results))
            refused = {why for ok, why in results if not ok}
            assert all(why.startswith("rate cap: at most 20") for why in refused), refused
            assert link.counts["rate_capped"] == len(results) - sent
            assert wait_for(lambda: len(fake.of_type("LANDING_TARGET")) == sent, 3.0)
        finally:
            link.stop()


def test_edge_run_on_a_fast_video_sends_at_the_cap(tmp_path):
    """A small video looped for 2.5 s gives hundreds of frames/s; the autopilot decodes at most --target-hz on
    average, and every capped frame's log line says why it was not sent."""
    assets = flat_assets(tmp_path, AGL_M)
    log_path = tmp_path / "cap.jsonl"
    port = free_udp_port()
    with LoopbackAutopilot(port, telemetry=True) as peer:
        assert main(["--camera", assets["video"], "--model", assets["model"], "--allow-unconfirmed", "--loop",
                     "--duration", "2.5", "--mav", f"udpout:127.0.0.1:{port}", "--target-hz", "10",
                     "--log", str(log_path)]) == 0
        wait_for(lambda: False, 0.3)
    decisions = read_decisions(log_path)
    sent = [d for d in decisions if d["sent"]]
    capped = [d for d in decisions if (d["not_sent_because"] or "").startswith("rate cap: at most 10")]
    received = peer.of_type("LANDING_TARGET")
    assert len(received) == len(sent) and 5 <= len(sent) <= 27            # <= 2.5 s x 10 Hz (+ 2 of credit)
    assert len(capped) > 2 * len(sent), (len(capped), len(sent))          # not vacuous: the video was faster


@pytest.mark.parametrize("argv, named", [(["--target-hz", "1"], "--target-hz"), (["--target-hz", "-3"], "--target-hz"),
                                         (["--geometry-timing", "later"], "--geometry-timing"),
                                         (["--geometry-width", "100"], "--geometry-width")])
def test_edge_run_names_a_bad_rate_or_timing(argv, named):
    from edge_landing.cli.run import config_from_args

    with pytest.raises(InputError, match=named):
        config_from_args(argv)
