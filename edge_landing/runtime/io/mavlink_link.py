"""The MAVLink link (ARCHITECTURE.md §8): heartbeat, LANDING_TARGET, STATUSTEXT out; telemetry in; signing; reconnect.

pymavlink is imported lazily (``load_mavutil``) after ``MAVLINK20=1`` is set, because it picks MAVLink 1 or
2 when it is first imported and the LANDING_TARGET extension fields exist only in MAVLink 2.
A dead link never stops the pipeline: errors are caught and counted, logged once per state change, the
connection is reopened with back-off, and sending resumes when the other end returns. Example::

    link = MavlinkLink(LinkConfig("udpout:127.0.0.1:14550"), TelemetryBuffer()).start()
    link.send_target(target, state)      # never raises
    link.stop()
"""
from __future__ import annotations

import logging
import math
import os
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple

import numpy as np

from edge_landing.runtime.core.choices import ChoiceEnum
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import Target, VehicleState
from edge_landing.runtime.io.telemetry import RANGEFINDER_DOWN, TelemetryBuffer

log = logging.getLogger(__name__)
NET_PREFIXES = ("udpout:", "udpin:", "udp:", "udpbcast:", "tcp:", "tcpin:")
FRAME_LOCAL_NED, FRAME_BODY_FRD = 1, 12
TARGET_TYPE_VISION_OTHER = 3
TELEMETRY_MESSAGES = ("ATTITUDE", "GLOBAL_POSITION_INT", "DISTANCE_SENSOR", "LOCAL_POSITION_NED")


class Autopilot(ChoiceEnum):
    ARDUPILOT = "ardupilot"
    PX4 = "px4"

    @classmethod
    def _label(cls) -> str:
        return "autopilot"


@dataclass(frozen=True)
class LinkConfig:
    url: str
    autopilot: Autopilot = Autopilot.ARDUPILOT
    system_id: int = 1             # companion computers share the vehicle's system id
    component_id: int = 191        # MAV_COMP_ID_ONBOARD_COMPUTER
    key_path: Optional[str] = None
    heartbeat_period_s: float = 1.0
    telemetry_rate_hz: float = 20.0
    error_quiet_s: float = 2.0     # the link counts as up again after this long without a send error
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 5.0


def load_mavutil():
    """pymavlink's mavutil with the MAVLink 2 dialect, whatever was imported before."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    if getattr(mavutil.mavlink, "WIRE_PROTOCOL_VERSION", "1.0") != "2.0":
        mavutil.set_dialect("ardupilotmega")  # pymavlink was imported earlier without MAVLINK20
    return mavutil


def check_url(url: str) -> None:
    """Fail fast on a connection string pymavlink would not understand."""
    if url.startswith(NET_PREFIXES):
        host_port = url.split(":", 1)[1]
        host, _, port = host_port.rpartition(":")
        if not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise InputError(f"MAVLink connection '{url}' needs host:port after the scheme, e.g. udpout:127.0.0.1:14550")
        return
    device = url.split(",", 1)[0]
    if device.startswith("/dev/") or device.upper().startswith("COM"):
        baud = url.split(",", 1)[1] if "," in url else "57600"
        if not baud.isdigit():
            raise InputError(f"MAVLink serial connection '{url}' has a bad baud rate '{baud}'; expected /dev/ttyUSB0,57600")
        return
    raise InputError(f"unsupported MAVLink connection '{url}'; expected udpout:host:port, udpin:host:port, "
                     f"tcp:host:port or a serial device like /dev/ttyUSB0,57600")


def load_signing_key(path: str) -> bytes:
    """A 32-byte MAVLink 2 signing key: raw bytes, or 64 hex characters in a text file."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"MAVLink signing key file {p} does not exist")
    data = p.read_bytes()
    if len(data) == 32:
        return data
    text = data.strip()
    try:
        key = bytes.fromhex(text.decode("ascii"))
    except (UnicodeDecodeError, ValueError):
        key = b""
    if len(key) != 32:
        raise InputError(f"MAVLink signing key {p} has {len(data)} bytes; expected 32 raw bytes or 64 hex characters")
    return key


def target_ned(target: Target, state: Optional[VehicleState]) -> Optional[np.ndarray]:
    """Absolute local NED of the target: vehicle position at capture + body vector rotated by the attitude."""
    if target.position_ned_m is not None:
        return np.asarray(target.position_ned_m, dtype=np.float64)
    if state is None or state.position_ned_m is None or target.position_body_frd_m is None:
        return None
    return np.asarray(state.position_ned_m) + state.attitude.ned_from_body() @ np.asarray(target.position_body_frd_m)


class MavlinkLink:
    """A MAVLink connection with its own receive/heartbeat thread; the send methods never raise."""

    def __init__(self, config: LinkConfig, telemetry: TelemetryBuffer):
        self.config = config
        self.telemetry = telemetry
        self.counts = {"targets": 0, "heartbeats": 0, "statustext": 0, "received": 0, "send_errors": 0,
                       "reconnects": 0, "skipped_px4_no_position": 0}
        self.peer: Optional[Tuple[int, int]] = None
        self._conn = None
        self._mavutil = None
        self._key: Optional[bytes] = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._last_error_s = -math.inf
        self._last_error = ""
        self._up_reported: Optional[bool] = None
        self._skip_reported = False
        self._last_telemetry_s = -math.inf
        self._last_request_s = -math.inf

    # -- life cycle -----------------------------------------------------------------------------------
    def start(self) -> MavlinkLink:
        check_url(self.config.url)
        if not self.config.url.startswith(NET_PREFIXES):
            try:
                import serial  # noqa: F401  (pymavlink needs pyserial for serial ports)
            except ImportError:
                raise InputError(f"MAVLink serial connection '{self.config.url}' needs pyserial: pip install pyserial") from None
        if self.config.key_path:
            self._key = load_signing_key(self.config.key_path)
        self._mavutil = load_mavutil()
        self._connect()  # a refused first connection is retried in the thread, not fatal
        self._thread = threading.Thread(target=self._run, name="mavlink", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=3.0)
        with self._lock:
            self._close()

    @property
    def up(self) -> bool:
        return self._conn is not None and time.monotonic() - self._last_error_s > self.config.error_quiet_s

    # -- sending (pipeline thread) ----------------------------------------------------------------------
    def send_target(self, target: Target, state: Optional[VehicleState]) -> Tuple[bool, str]:
        """Send LANDING_TARGET for a valid target; returns (sent, why not)."""
        if not target.valid or target.position_body_frd_m is None:
            return False, target.reason or "no target"
        body = np.asarray(target.position_body_frd_m, dtype=np.float64)
        distance = float(np.linalg.norm(body))
        if not np.isfinite(body).all() or distance <= 0:
            return False, "target position is not finite"
        if self.config.autopilot is Autopilot.PX4:
            xyz = target_ned(target, state)
            if xyz is None:
                self.counts["skipped_px4_no_position"] += 1
                if not self._skip_reported:
                    log.warning("px4 mode: no LOCAL_POSITION_NED telemetry matched frame %d, so no LANDING_TARGET "
                                "is sent (PX4 needs the target's absolute local position)", target.frame_id)
                    self._skip_reported = True
                return False, "px4 needs LOCAL_POSITION_NED telemetry"
            self._skip_reported = False
            frame = FRAME_LOCAL_NED
        else:
            xyz, frame = body, FRAME_BODY_FRD
        m = self._mavutil.mavlink
        msg = m.MAVLink_landing_target_message(
            int(target.capture_time_s * 1e6), 0, frame, _finite(target.angle_x_rad), _finite(target.angle_y_rad),
            distance, _finite(target.size_x_rad), _finite(target.size_y_rad), float(xyz[0]), float(xyz[1]),
            float(xyz[2]), [1.0, 0.0, 0.0, 0.0], TARGET_TYPE_VISION_OTHER, 1)
        if self._send(msg):
            self.counts["targets"] += 1
            return True, ""
        return False, "link down"

    def send_status(self, text: str, severity: int = 6) -> bool:
        """STATUSTEXT (severity 6 = INFO), at most 50 characters."""
        msg = self._mavutil.mavlink.MAVLink_statustext_message(severity, text[:50].encode("ascii", "replace"))
        ok = self._send(msg)
        self.counts["statustext"] += ok
        return ok

    def _send(self, msg) -> bool:
        with self._lock:
            if self._conn is None:
                return False
            try:
                self._conn.mav.send(msg)
                return True
            except BlockingIOError:
                return False  # socket buffer full: drop this message, the link itself is fine
            except (OSError, ValueError) as exc:  # refused / reset / serial gone
                if not self.config.url.startswith(("udpout:", "udpin:", "udp:", "udpbcast:")):
                    self._close()  # a stream connection is dead after an error: the thread reopens it
                self._fault(f"send failed: {exc}")
                return False

    # -- connection -----------------------------------------------------------------------------------
    def _connect(self) -> bool:
        c = self.config
        kwargs = dict(source_system=c.system_id, source_component=c.component_id)
        if c.url.startswith("tcp:"):
            kwargs.update(retries=0)
        device, baud = c.url, 57600
        if not c.url.startswith(NET_PREFIXES) and "," in c.url:
            device, baud = c.url.split(",", 1)[0], int(c.url.split(",", 1)[1])
        try:
            conn = self._mavutil.mavlink_connection(device, baud=baud, **kwargs)
        except Exception as exc:  # pymavlink raises OSError, serial.SerialException or bare Exception
            self._fault(f"cannot connect: {exc}")
            return False
        try:
            if c.url.startswith("udpout:"):
                # A connected UDP socket reports 'port unreachable' as ConnectionRefusedError on the next send or
                # receive; pymavlink's receive swallows it, so ours lets it through.
                conn.port.connect(conn.destination_addr)
                conn.recv = _strict_udp_recv(conn.port)
        except OSError as exc:  # e.g. the host name does not resolve (yet): retried like a refused connection
            conn.close()
            self._fault(f"cannot connect: {exc}")
            return False
        if c.url.startswith(("udpout:", "tcp:")):
            conn.mav.file = _RaisingWriter(conn.port)  # pymavlink's own write swallows socket errors
        if c.url.startswith("tcp:"):
            # pymavlink only prints on a closed TCP peer (and keeps printing); raise so we reconnect.
            conn.handle_eof = conn.handle_disconnect = _raise_closed
        if self._key is not None:
            conn.setup_signing(self._key, sign_outgoing=True)
        with self._lock:
            self._conn = conn
        return True

    def _close(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            except Exception:  # closing a dead connection may itself fail; nothing to do about it
                pass
            self._conn = None

    def _fault(self, reason: str) -> None:
        self.counts["send_errors"] += 1
        self._last_error_s = time.monotonic()
        self._last_error = reason
        self._report()

    def _report(self) -> None:
        up = self.up
        if up != self._up_reported:
            if up:
                log.info("MAVLink link %s is up", self.config.url)
            else:
                log.warning("MAVLink link %s is down (%s); retrying with back-off, the pipeline keeps running",
                            self.config.url, self._last_error)
            self._up_reported = up

    # -- the thread -----------------------------------------------------------------------------------
    def _run(self) -> None:
        backoff_s = self.config.reconnect_min_s
        next_heartbeat_s = 0.0
        while not self._stop.is_set():
            if self._conn is None:
                if self._stop.wait(backoff_s):
                    break
                if self._connect():
                    self.counts["reconnects"] += 1
                    backoff_s = self.config.reconnect_min_s
                else:
                    backoff_s = min(backoff_s * 2.0, self.config.reconnect_max_s)
                continue
            now = time.monotonic()
            if now >= next_heartbeat_s:
                self._heartbeat()
                next_heartbeat_s = now + self.config.heartbeat_period_s
            self._request_telemetry(now)
            conn = self._conn
            try:
                msg = conn.recv_match(blocking=True, timeout=0.05)
            except ConnectionRefusedError as exc:  # UDP: nobody listening; the socket itself is fine
                self._fault(f"nobody listening ({exc.strerror or exc})")
                continue
            except Exception as exc:  # TCP reset, serial unplugged: close and reconnect
                with self._lock:
                    if self._conn is conn:
                        self._close()
                self._fault(f"receive failed: {exc}")
                continue
            if msg is not None:
                self._handle(msg)
            self._report()

    def _heartbeat(self) -> None:
        m = self._mavutil.mavlink
        if self._send(m.MAVLink_heartbeat_message(m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 0, 0,
                                                  m.MAV_STATE_ACTIVE, 3)):
            self.counts["heartbeats"] += 1

    def _request_telemetry(self, now: float) -> None:
        """Ask the autopilot for the messages we need until they flow (and again if they stop)."""
        if self.peer is None or now - self._last_telemetry_s < 1.0 or now - self._last_request_s < 3.0:
            return
        self._last_request_s = now
        m = self._mavutil.mavlink
        interval_us = 1e6 / self.config.telemetry_rate_hz
        for name in TELEMETRY_MESSAGES:
            msg_id = getattr(m, f"MAVLINK_MSG_ID_{name}")
            self._send(m.MAVLink_command_long_message(self.peer[0], self.peer[1], m.MAV_CMD_SET_MESSAGE_INTERVAL,
                                                      0, msg_id, interval_us, 0, 0, 0, 0, 0))

    def _handle(self, msg) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return
        self.counts["received"] += 1
        arrival = time.monotonic()
        t = self.telemetry
        m = self._mavutil.mavlink
        if kind == "HEARTBEAT":
            if msg.autopilot != m.MAV_AUTOPILOT_INVALID and msg.type != m.MAV_TYPE_GCS and self.peer is None:
                self.peer = (msg.get_srcSystem(), msg.get_srcComponent())
                log.info("autopilot found: system %d component %d", *self.peer)
            return
        if kind not in TELEMETRY_MESSAGES:
            return
        self._last_telemetry_s = arrival
        if kind == "ATTITUDE":
            t.add_attitude(msg.roll, msg.pitch, msg.yaw, msg.time_boot_ms, arrival)
        elif kind == "LOCAL_POSITION_NED":
            t.add_position(msg.x, msg.y, msg.z, msg.time_boot_ms, arrival)
        elif kind == "GLOBAL_POSITION_INT":
            t.add_relative_alt(msg.relative_alt / 1000.0, msg.time_boot_ms, arrival)
        elif kind == "DISTANCE_SENSOR" and msg.orientation == RANGEFINDER_DOWN:
            if msg.min_distance <= msg.current_distance <= msg.max_distance:
                t.add_rangefinder(msg.current_distance / 100.0, msg.time_boot_ms, arrival)


class _RaisingWriter:
    """Stands in for pymavlink's file object so that socket errors reach us instead of being swallowed."""

    def __init__(self, sock: socket.socket):
        self.sock = sock

    def write(self, buf: bytes) -> None:
        self.sock.send(buf)


def _strict_udp_recv(sock: socket.socket):
    def recv(n=None) -> bytes:
        try:
            return sock.recv(65535)
        except BlockingIOError:
            return b""
    return recv


def _raise_closed() -> None:
    raise ConnectionResetError("connection closed by the other end")


def _finite(value: float) -> float:
    return float(value) if math.isfinite(value) else 0.0
