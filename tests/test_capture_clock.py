"""A camera device's capture time from the driver's buffer stamp (runtime/io/capture_clock.py), and a live
camera's latency that its stamps leave out (edge-run --camera-delay).

No V4L2 device exists here; the stamps are the numbers OpenCV's V4L2 backend reports as CAP_PROP_POS_MSEC
(the dequeued buffer's time stamp, ms)."""
import logging
import time

import numpy as np
import pytest

from edge_landing.runtime.io.capture_clock import DriverClock
from edge_landing.runtime.io.grabber import Grabber
from edge_landing.runtime.io.sources import Reader, SourceConfig, SourceKind


def test_a_monotonic_driver_stamp_is_the_capture_time():
    clock = DriverClock("/dev/video0")
    assert clock.capture_time_s(1000.0 * 1000.0 - 42.0, 1000.0) == (pytest.approx(999.958), "")
    assert clock.capture_time_s(1000.033 * 1000.0 - 40.0, 1000.033) == (pytest.approx(999.993), "")
    assert (clock.used, clock.on_arrival) == (2, 0) and clock.latency_s == pytest.approx(0.040)


@pytest.mark.parametrize("driver_ms, why", [
    (0.0, "no time stamp"),                       # a driver without stamps
    (float("nan"), "no time stamp"),
    (1_700_000_000_000.0, "in the future"),        # the wall clock (epoch ms), not CLOCK_MONOTONIC
    (400_000.0, "old when read"),                  # another clock that started earlier, or a held buffer
])
def test_a_stamp_not_on_this_clock_leaves_the_frame_stamped_on_arrival(driver_ms, why, caplog):
    clock = DriverClock("/dev/video0")
    with caplog.at_level(logging.WARNING, logger="edge_landing.runtime.io.capture_clock"):
        assert clock.capture_time_s(driver_ms, 1000.0) == (1000.0, "")
        assert clock.capture_time_s(driver_ms, 1000.1) == (1000.1, "")
    assert clock.on_arrival == 2
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and why in lines[0]                 # said once, with the reason


def test_a_frame_without_a_usable_stamp_keeps_the_order_of_capture_times():
    """A driver repeating a buffer's stamp (or going back) would put two images at one pose, and a capture time
    that goes back wipes motion geometry's evidence: such a frame is placed at its arrival less the latency the
    driver's stamps showed, and when even that is not later than the previous frame it is marked invalid."""
    clock = DriverClock("/dev/video0")
    assert clock.capture_time_s(999_950.0, 1000.0) == (pytest.approx(999.95), "")        # 50 ms latency
    assert clock.capture_time_s(999_950.0, 1000.033) == (pytest.approx(999.983), "")     # repeated stamp
    t, problem = clock.capture_time_s(999_940.0, 1000.033)     # went back, read in the same instant: no later
    assert t == pytest.approx(999.983) and "no later than the previous frame" in problem
    # The driver's stamps resume (no lock-in on the estimates), in order.
    assert clock.capture_time_s(1_000_016.0, 1000.066) == (pytest.approx(1000.016), "")
    assert clock.capture_time_s(1_000_049.0, 1000.099) == (pytest.approx(1000.049), "")
    assert (clock.used, clock.on_arrival) == (3, 2)


class _StampedCamera(Reader):
    """A live source whose reader knows when each image was taken (as VideoReader does from the driver)."""

    name = "stamped"

    def read(self):
        time.sleep(0.005)
        self.capture_time_s = time.monotonic() - 0.030
        return np.zeros((8, 8, 3), np.uint8)


@pytest.mark.parametrize("kind, stamped, expected_age_s", [
    (SourceKind.STREAM, False, 0.25),     # RTSP: stamped on arrival, less the stream's latency
    (SourceKind.DEVICE, True, 0.28),      # a driver's stamp (30 ms old), less what it leaves out
    (SourceKind.FILE, False, 0.0),        # recorded: stamped when taken, no latency to remove
])
def test_camera_delay_is_taken_off_a_live_cameras_time_stamps(kind, stamped, expected_age_s):
    from tests.test_sources import FastCamera

    grabber = Grabber(SourceConfig("cam", kind, delay_s=0.25),
                      opener=lambda _c: _StampedCamera() if stamped else FastCamera()).start()
    try:
        frame = grabber.next(timeout_s=2.0)
        received = time.monotonic()
    finally:
        grabber.stop()
    assert frame is not None
    assert expected_age_s <= received - frame.capture_time_s < expected_age_s + 0.1


def test_camera_delay_is_refused_where_it_means_nothing(tmp_path, capsys):
    from edge_landing.cli.run import main as run_main
    from tests.helpers import one_line_error

    video = tmp_path / "flight.mp4"
    video.write_bytes(b"\0")
    one_line_error(capsys, run_main, ["--camera", video, "--camera-delay", "0.1"], "--camera-delay is a live camera")
    one_line_error(capsys, run_main, ["--camera-delay", "0.1"], "--camera-delay")                  # the sim camera
    one_line_error(capsys, run_main, ["--camera", "rtsp://cam/1", "--camera-delay", "3"], "--camera-delay")
