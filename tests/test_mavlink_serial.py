"""The serial MAVLink path (``--mav /dev/ttyX,BAUD``) over a real pseudo-terminal pair: pyserial opens the
slave end exactly as it would a USB/UART autopilot link; a pymavlink parser reads the master end."""
from __future__ import annotations

import os
import select
import sys
import time

import numpy as np
import pytest

pytest.importorskip("serial")
if not sys.platform.startswith("linux"):
    pytest.skip("pseudo-terminals as serial ports: Linux only", allow_module_level=True)

from edge_landing.runtime.core.messages import Target  # noqa: E402
from edge_landing.runtime.io.autopilot_setup import SetupCheck
from edge_landing.runtime.io.mavlink_link import LinkConfig, MavlinkLink, load_mavutil  # noqa: E402
from edge_landing.runtime.io.telemetry import TelemetryBuffer  # noqa: E402


class _FdWriter:
    def __init__(self, fd: int):
        self.fd = fd

    def write(self, buf: bytes) -> None:
        os.write(self.fd, buf)


def _read_messages(fd: int, parser, seconds: float) -> list:
    got, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        ready, _, _ = select.select([fd], [], [], 0.05)
        if ready:
            for byte_msg in parser.parse_buffer(os.read(fd, 4096)) or []:
                got.append(byte_msg)
        if any(m.get_type() == "LANDING_TARGET" for m in got) and any(m.get_type() == "HEARTBEAT" for m in got):
            break
    return got


def test_landing_target_and_heartbeat_over_a_serial_port():
    master, slave = os.openpty()
    try:
        import tty
        tty.setraw(master)
        # This autopilot answers no PARAM_REQUEST_READ: the setup check (tests/test_autopilot_setup.py) would hold
        # its first targets for up to 1 s.
        link = MavlinkLink(LinkConfig(f"{os.ttyname(slave)},115200", setup_check=SetupCheck.OFF),
                           TelemetryBuffer()).start()
        mavutil = load_mavutil()
        parser = mavutil.mavlink.MAVLink(None)
        # The autopilot's side speaks first (a HEARTBEAT): a target leaves only while the autopilot is heard.
        autopilot = mavutil.mavlink.MAVLink(_FdWriter(master), srcSystem=1, srcComponent=1)
        end = time.monotonic() + 5.0
        while link.peer is None and time.monotonic() < end:
            autopilot.heartbeat_send(2, 3, 0, 0, 4)  # quadrotor, ArduPilot
            time.sleep(0.1)
        assert link.peer == (1, 1)
        target = Target(0, time.monotonic(), True, position_body_frd_m=np.array([6.0, -1.0, 12.0]),
                        angle_x_rad=-0.07, angle_y_rad=0.44, size_x_rad=0.2, size_y_rad=0.2, clearance_m=3.0)
        try:
            for _ in range(5):
                link.send_target(target, None)
                time.sleep(0.02)
            messages = _read_messages(master, parser, 5.0)
        finally:
            link.stop()
    finally:
        os.close(master)
        os.close(slave)
    kinds = {m.get_type() for m in messages}
    assert {"HEARTBEAT", "LANDING_TARGET"} <= kinds, kinds
    lt = next(m for m in messages if m.get_type() == "LANDING_TARGET")
    assert lt.position_valid == 1
    assert np.allclose([lt.x, lt.y, lt.z], [6.0, -1.0, 12.0], atol=1e-5)
    assert abs(lt.distance - float(np.linalg.norm([6.0, -1.0, 12.0]))) < 1e-4
