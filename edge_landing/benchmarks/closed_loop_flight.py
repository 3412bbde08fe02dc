"""The closed-loop driver's MAVLink side (benchmarks/closed_loop.py): commands to the autopilot and the flown path.

Frames: the autopilot's local NED (metres); times on this computer's monotonic clock.
"""
from __future__ import annotations

import logging
import time
from typing import Any, Callable, List, Tuple

import numpy as np

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.io.mavlink_link import Autopilot, check_url, load_mavutil

log = logging.getLogger("closed_loop")


class Flight:
    """The driver's MAVLink side: commands, and the path recorded from LOCAL_POSITION_NED."""

    def __init__(self, url: str, autopilot: Autopilot):
        check_url(url)
        self.mavutil: Any = load_mavutil()
        self.conn = self.mavutil.mavlink_connection(url, source_system=255, source_component=190)
        self.autopilot = autopilot
        self.path: List[Tuple[float, float, float, float]] = []          # (local monotonic s, n, e, d) local NED
        self.armed = False
        self.messages: List[str] = []

    def pump(self, timeout_s: float = 0.05) -> None:
        msg = self.conn.recv_match(blocking=True, timeout=timeout_s)
        while msg is not None:
            kind = msg.get_type()
            if kind == "LOCAL_POSITION_NED":
                self.path.append((time.monotonic(), msg.x, msg.y, msg.z))
            elif kind == "HEARTBEAT" and msg.autopilot != self.mavutil.mavlink.MAV_AUTOPILOT_INVALID:
                # the autopilot itself (not edge-run's or a camera's heartbeat routed by a MAVProxy)
                self.armed = bool(msg.base_mode & self.mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                self.conn.target_system, self.conn.target_component = msg.get_srcSystem(), msg.get_srcComponent()
            elif kind == "STATUSTEXT":
                self.messages.append(msg.text)
                log.info("autopilot: %s", msg.text)
            msg = self.conn.recv_match(blocking=False)

    def wait(self, what: str, done: Callable[[], bool], timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while not done():
            if time.monotonic() > deadline:
                raise InputError(f"closed loop: {what} did not happen within {timeout_s:.0f} s")
            self.pump()

    def heartbeat(self) -> None:
        m = self.mavutil.mavlink
        self.conn.mav.heartbeat_send(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def has_position(self) -> bool:
        return bool(self.path)

    def position(self) -> np.ndarray:
        """The latest local NED position (call after has_position)."""
        return np.array(self.path[-1][1:]) if self.path else np.full(3, np.nan)

    def command(self, command: int, *params: float) -> None:
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(self.conn.target_system, self.conn.target_component, command, 0, *p)

    def set_mode(self, name: str) -> None:
        mapping = self.conn.mode_mapping() or {}
        if name not in mapping:
            raise InputError(f"closed loop: the autopilot has no {name} mode (modes: {sorted(mapping)})")
        self.conn.set_mode(mapping[name])

    def goto(self, ned: np.ndarray, yaw_rad: float) -> None:
        north, east, down = (float(v) for v in ned)
        m = self.mavutil.mavlink
        mask = 0b0000_1001_1111_1000  # positions + yaw; ignore velocity, acceleration, yaw rate
        self.conn.mav.set_position_target_local_ned_send(0, self.conn.target_system, self.conn.target_component,
                                                         m.MAV_FRAME_LOCAL_NED, mask, north, east, down,
                                                         0, 0, 0, 0, 0, 0, yaw_rad, 0)

    def close(self) -> None:
        self.conn.close()
