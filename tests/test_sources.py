"""Frame sources and the grabber thread: real OpenCV files, real threads."""
from __future__ import annotations

import logging
import re
import time

import cv2
import numpy as np
import pytest

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.io.grabber import Grabber
from edge_landing.runtime.io.sources import Reader, SourceConfig, SourceKind, check_source_exists, sim_style_seed
from tests.run_helpers import write_video


def drain(grabber: Grabber, limit: int = 1000, timeout_s: float = 5.0):
    frames, end = [], time.monotonic() + timeout_s
    while len(frames) < limit and time.monotonic() < end:
        f = grabber.next(timeout_s=0.5)
        if f is not None:
            frames.append(f)
        elif grabber.ended:
            break
    return frames


@pytest.mark.parametrize("camera, kind", [("/dev/video0", SourceKind.DEVICE), ("2", SourceKind.DEVICE),
                                          ("rtsp://10.0.0.1/cam", SourceKind.STREAM),
                                          ("v4l2src ! videoconvert ! appsink", SourceKind.STREAM),
                                          ("sim", SourceKind.SIM), ("frames/*.png", SourceKind.FOLDER),
                                          ("flight.mp4", SourceKind.FILE)])
def test_kind_from_string(camera, kind):
    assert SourceKind.from_string(camera) is kind


def test_video_file_gives_every_frame_with_ids_and_monotonic_times(tmp_path):
    path = write_video(tmp_path / "v.avi", frames=9)
    grabber = Grabber(SourceConfig.from_string(str(path))).start()
    frames = drain(grabber)
    grabber.stop()
    assert [f.frame_id for f in frames] == list(range(9))
    assert all(b.capture_time_s > a.capture_time_s for a, b in zip(frames, frames[1:]))
    assert frames[0].rgb.shape == (96, 128, 3) and frames[0].rgb.dtype == np.uint8
    assert grabber.ended and grabber.drops == 0


def test_loop_repeats_a_file(tmp_path):
    path = write_video(tmp_path / "v.avi", frames=4)
    grabber = Grabber(SourceConfig.from_string(str(path), loop=True)).start()
    frames = drain(grabber, limit=10)
    grabber.stop()
    assert len(frames) == 10 and [f.frame_id for f in frames] == list(range(10))


def test_truncated_video_ends_cleanly_with_a_warning(tmp_path, caplog):
    path = write_video(tmp_path / "v.avi", frames=30)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with caplog.at_level(logging.WARNING):
        grabber = Grabber(SourceConfig.from_string(str(path))).start()
        frames = drain(grabber)
        grabber.stop()
    assert 0 < len(frames) < 30
    assert grabber.ended
    assert any("ended early" in r.message for r in caplog.records)


def test_garbage_video_is_one_clear_error(tmp_path):
    path = tmp_path / "broken.mp4"
    path.write_bytes(b"\x00\x01not a video" * 50)
    with pytest.raises(InputError, match="cannot open video file"):
        Grabber(SourceConfig.from_string(str(path))).start()


def test_missing_device_and_file_are_clear_errors(tmp_path):
    with pytest.raises(InputError, match="/dev/video97 not found"):
        Grabber(SourceConfig.from_string("/dev/video97")).start()
    with pytest.raises(InputError, match="does not exist"):
        Grabber(SourceConfig.from_string(str(tmp_path / "nope.mp4"))).start()


def test_image_folder_and_glob_skip_corrupt_images(tmp_path, caplog):
    rng = np.random.default_rng(1)
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"{i:03d}.png"), rng.integers(0, 255, (32, 40, 3), dtype=np.uint8))
    (tmp_path / "001b.png").write_bytes(b"corrupt")
    with caplog.at_level(logging.WARNING):
        grabber = Grabber(SourceConfig.from_string(str(tmp_path))).start()
        frames = drain(grabber)
        grabber.stop()
    assert len(frames) == 3 and any("001b.png" in r.message for r in caplog.records)
    grabber = Grabber(SourceConfig.from_string(str(tmp_path / "00[02].png"))).start()
    assert len(drain(grabber)) == 2
    grabber.stop()
    with pytest.raises(InputError, match="no images found"):
        Grabber(SourceConfig.from_string(str(tmp_path / "*.jpg"))).start()


def test_an_image_repeated_bit_for_bit_by_a_camera_device_is_invalid(tmp_path, caplog):
    """A frozen capture card repeats its last buffer; a sensor's noise makes real exposures differ."""
    rng = np.random.default_rng(2)
    a, b, c = (rng.integers(0, 255, (48, 64, 3), dtype=np.uint8) for _ in range(3))
    path = tmp_path / "frozen.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    for img in (a, a, b, b, b, b, c):
        writer.write(img)
    writer.release()
    assert SourceConfig.from_string("/dev/video0").checks_repeats
    assert not SourceConfig.from_string(str(path)).checks_repeats   # a recorded hover may repeat an image
    with caplog.at_level(logging.WARNING):
        grabber = Grabber(SourceConfig.from_string(str(path), repeats_invalid=True)).start()
        frames = drain(grabber)
        grabber.stop()
    assert [f.valid for f in frames] == [True, False, True, False, False, False, True]
    assert all("stale buffer" in f.reason for f in frames if not f.valid)
    said = [r.message for r in caplog.records if "invalid" in r.message]
    assert len(said) == 4, said   # each run of invalid frames once at its start and once at its end
    assert said[3].startswith("3 frame(s)")
    grabber = Grabber(SourceConfig.from_string(str(path))).start()
    assert all(f.valid for f in drain(grabber))
    grabber.stop()


class FastCamera(Reader):
    """A live source producing frames as fast as it can; fails once after ``fail_after`` frames."""

    opened = 0

    def __init__(self, fail_after: int = 0):
        FastCamera.opened += 1
        self.fail_after, self.count = fail_after, 0
        self.name = "fast"

    def read(self):
        self.count += 1
        if self.fail_after and self.count > self.fail_after:
            raise OSError("camera unplugged")
        time.sleep(0.002)
        return np.full((16, 16, 3), self.count % 255, np.uint8)


def test_live_source_keeps_newest_frame_and_counts_drops():
    config = SourceConfig("fake-live", SourceKind.DEVICE)
    grabber = Grabber(config, opener=lambda c: FastCamera()).start()
    seen = []
    for _ in range(5):
        time.sleep(0.05)  # a slow pipeline
        seen.append(grabber.next(timeout_s=1.0))
    grabber.stop()
    assert all(f is not None for f in seen)
    assert grabber.drops > 0
    assert grabber.drops + len(seen) <= grabber.grabbed + 1
    assert seen[-1].frame_id > seen[0].frame_id + 4  # intermediate frames were dropped, the newest kept


def test_lost_camera_is_reopened_with_backoff_and_the_loop_goes_on(caplog):
    FastCamera.opened = 0
    config = SourceConfig("fake-live", SourceKind.DEVICE, reopen_min_s=0.05, reopen_max_s=0.1)
    with caplog.at_level(logging.WARNING):
        grabber = Grabber(config, opener=lambda c: FastCamera(fail_after=5)).start()
        frames = drain(grabber, limit=15, timeout_s=5.0)
        ended_while_running = grabber.ended
        grabber.stop()
    assert len(frames) == 15 and not ended_while_running
    assert grabber.faults >= 2 and FastCamera.opened >= 3
    assert any("reopening" in r.message for r in caplog.records)
    assert any("is back" in r.message for r in caplog.records)


def test_sim_source_without_the_extra_names_it(monkeypatch):
    import sys

    from edge_landing.runtime.core.errors import MissingExtraError

    monkeypatch.setitem(sys.modules, "edge_landing.sim", None)  # as if the [sim] extra were not installed
    with pytest.raises(MissingExtraError, match=r"edge-landing\[sim\]"):
        Grabber(SourceConfig.from_string("sim")).start()


@pytest.mark.parametrize("missing", ["trimesh", "embreex"])
def test_sim_source_checks_the_ray_caster_before_building_a_world(monkeypatch, caplog, missing):
    import sys

    from edge_landing.runtime.core.errors import MissingExtraError

    monkeypatch.setitem(sys.modules, missing, None)
    with caplog.at_level("INFO"), pytest.raises(MissingExtraError, match=rf"'{missing}'.*edge-landing\[sim\]"):
        Grabber(SourceConfig.from_string("sim")).start()
    assert not any("building" in r.getMessage() for r in caplog.records)


@pytest.mark.slow
def test_sim_source_gives_frames_and_perfect_telemetry():
    from edge_landing.runtime.io.telemetry import TelemetryBuffer

    telemetry = TelemetryBuffer()
    grabber = Grabber(SourceConfig.from_string("sim:suburban:1", width=64, height=48, fps=20.0),
                      telemetry=telemetry).start()
    frames = drain(grabber, limit=4, timeout_s=60.0)
    grabber.stop()
    assert len(frames) == 4 and frames[0].rgb.shape == (48, 64, 3)
    state = telemetry.state_at(frames[-1].capture_time_s)
    assert state is not None and state.position_ned_m is not None and 20.0 < state.agl_m < 120.0
    assert grabber.reader.intrinsics.width == 64


def _poses_csv(path, frames: int, dt_s: float) -> str:
    lines = ["frame,t,north,east,down,roll,pitch,yaw,agl"]
    lines += [f"{k},{k * dt_s:.3f},{2.0 * k},0,-40,0,0,0,40" for k in range(frames)]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


@pytest.mark.parametrize("pause_s", [0.0, 0.25])
def test_replayed_flight_frames_carry_the_flights_own_times(tmp_path, pause_s):
    """A replay with its poses is stamped with the flight's time on a monotonic base fixed at its start, so
    the spacing of capture times (what motion geometry pairs by) does not depend on how fast frames are taken;
    telemetry matches each frame exactly, and stays fresh because freshness is judged on the frame's clock
    (the pipeline's rule: now minus the frame's clock lag), however far the replay falls behind."""
    from edge_landing.runtime.io.telemetry import TelemetryBuffer

    video = write_video(tmp_path / "flight.avi", frames=6)
    poses = _poses_csv(tmp_path / "poses.csv", 6, 0.1)
    telemetry = TelemetryBuffer()
    grabber = Grabber(SourceConfig.from_string(str(video), poses_csv=poses), telemetry=telemetry).start()
    frames, matches = [], []
    while (f := grabber.next(timeout_s=2.0)) is not None:
        frames.append(f)
        matches.append(telemetry.lookup(f.capture_time_s, time.monotonic() - f.clock_lag_s))
        time.sleep(pause_s)   # a slow pipeline: the replay falls behind the flight's time
    grabber.stop()
    assert len(frames) == 6
    steps = np.diff([f.capture_time_s for f in frames])
    assert np.allclose(steps, 0.1, atol=1e-9), steps
    assert all(m.fresh for m in matches), [m.reason for m in matches]
    assert [float(m.state.position_ned_m[0]) for m in matches] == [2.0 * k for k in range(6)]
    lags = [f.clock_lag_s for f in frames]
    if pause_s:
        assert lags[-1] > lags[0] + 0.5  # about 5 × (0.25 - 0.1) s behind real time by the end


@pytest.mark.parametrize("camera, expected", [
    ("sim", ("suburban", 0)),
    ("sim:urban:3", ("urban", 3)),
    ("sim:7", ("suburban", 7)),
    ("sim-follow:urban:7:gimbal@udpin:127.0.0.1:15000", ("urban", 7)),   # neither "gimbal" nor the URL is a style
])
def test_sim_style_and_seed_from_the_camera_argument(camera, expected):
    assert sim_style_seed(camera) == expected


@pytest.mark.parametrize("camera, message", [
    ("/dev/video97", "/dev/video97 not found"),
    ("/nonexistent/flight.mp4", "video file /nonexistent/flight.mp4 does not exist"),
    ("/nonexistent/*.jpg", "no images found at /nonexistent/*.jpg"),
])
def test_a_missing_input_is_told_without_opening_anything(camera, message):
    with pytest.raises(InputError, match=re.escape(message)):
        check_source_exists(SourceConfig.from_string(camera))


def test_inputs_that_are_there_pass_the_existence_check(tmp_path):
    (tmp_path / "a.png").write_bytes(b"not opened by the check")
    video = tmp_path / "v.mp4"
    video.write_bytes(b"")
    for camera in (str(tmp_path), str(tmp_path / "*.png"), str(video), "rtsp://192.0.2.1/stream"):
        check_source_exists(SourceConfig.from_string(camera))
