"""Helpers for the streaming-runtime tests: a flat-ground ONNX model, a small video, a loopback autopilot."""
from __future__ import annotations

import socket
import threading
import time
from pathlib import Path
from typing import List, Optional

import cv2
import numpy as np

from edge_landing.benchmarks.flat_model import flat_ground_model, ground_plane_depth
from tests.fake_autopilot import answer_param_request

__all__ = ["flat_ground_model", "ground_plane_depth"]  # re-exported: the tests import them from here


def write_video(path: Path, frames: int = 12, height: int = 96, width: int = 128, fourcc: str = "MJPG",
                fps: float = 10.0) -> Path:
    """A small textured video written with OpenCV (MJPG in .avi survives truncation frame by frame)."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (width, height))
    assert writer.isOpened(), f"OpenCV cannot write {path}"
    rng = np.random.default_rng(0)
    base = rng.integers(60, 200, size=(height, width, 3), dtype=np.uint8)
    for i in range(frames):
        img = np.roll(base, i, axis=1)
        cv2.putText(img, str(i), (5, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1)
        writer.write(img)
    writer.release()
    return path


def flat_assets(folder: Path, agl_m: float = 10.0, frames: int = 8) -> dict:
    """What the edge-run tests fly: the flat-ground model ``agl_m`` below and a small video of ``frames``
    frames, both written into ``folder`` (``{"model": str, "video": str, "dir": folder}``)."""
    return {"model": str(flat_ground_model(folder / "flat.onnx", agl_m=agl_m)),
            "video": str(write_video(folder / "v.avi", frames)), "dir": folder}


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LoopbackAutopilot:
    """A pymavlink peer on ``udpin:127.0.0.1:PORT``: records every message; optionally plays an autopilot
    (HEARTBEAT + ATTITUDE + LOCAL_POSITION_NED + GLOBAL_POSITION_INT at ``rate_hz``) once edge-run is heard.
    As ``ardupilot`` (TEST DOUBLE) it answers PARAM_REQUEST_READ for a right precision-landing setup, as
    tests.fake_autopilot does."""

    def __init__(self, port: int, telemetry: bool = False, position_ned=(5.0, -3.0, -10.0), yaw_rad: float = 0.0,
                 rate_hz: float = 50.0, autopilot: str = "ardupilot"):
        from edge_landing.runtime.io.mavlink_link import load_mavutil

        self.mavutil = load_mavutil()
        self.conn = self.mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=1)
        self.telemetry, self.position_ned, self.yaw_rad, self.rate_hz = telemetry, position_ned, yaw_rad, rate_hz
        self.autopilot = autopilot
        self.messages: List = []
        self.arrivals: List[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._t0 = time.monotonic()

    def __enter__(self) -> LoopbackAutopilot:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=3)
        self.conn.close()

    def of_type(self, kind: str) -> list:
        return [m for m in list(self.messages) if m.get_type() == kind]

    def _run(self) -> None:
        m = self.mavutil.mavlink
        next_send = 0.0
        while not self._stop.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.01)
            if msg is not None and msg.get_type() != "BAD_DATA":
                self.messages.append(msg)
                self.arrivals.append(time.monotonic())
                if self.autopilot == "ardupilot" and self.conn.clients:
                    answer_param_request(self.conn.mav, msg)
            now = time.monotonic()
            if self.telemetry and self.conn.clients and now >= next_send:
                next_send = now + 1.0 / self.rate_hz
                boot_ms = int((now - self._t0) * 1000)
                n, e, d = self.position_ned
                kind = m.MAV_AUTOPILOT_ARDUPILOTMEGA if self.autopilot == "ardupilot" else m.MAV_AUTOPILOT_PX4
                self.conn.mav.heartbeat_send(m.MAV_TYPE_QUADROTOR, kind, 0, 0, m.MAV_STATE_ACTIVE)
                self.conn.mav.attitude_send(boot_ms, 0.0, 0.0, self.yaw_rad, 0.0, 0.0, 0.0)
                self.conn.mav.local_position_ned_send(boot_ms, n, e, d, 0.0, 0.0, 0.0)
                self.conn.mav.global_position_int_send(boot_ms, 0, 0, 0, int(-d * 1000), 0, 0, 0, 0)


def wait_for(predicate, timeout_s: float = 10.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def wait_until_sendable(link, timeout_s: float = 5.0) -> bool:
    """The link is up and its setup read is done: the read runs beside the link coming up and, on a loaded
    machine, can finish after a test's first target, which is then held (rightly) instead of sent."""
    return wait_for(lambda: link.up and (link.setup is None or not link.setup.hold_reason(time.monotonic())),
                    timeout_s)


def last(items: list) -> Optional[object]:
    return items[-1] if items else None


def read_decisions(path) -> list:
    """The per-frame decision lines of an ``edge-run --log`` file (the first line is the run record)."""
    import json

    lines = [json.loads(line) for line in Path(path).read_text().splitlines()]
    assert lines and "run" in lines[0], "the first --log line must be the run record"
    return lines[1:]
