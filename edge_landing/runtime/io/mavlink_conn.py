"""Opening a pymavlink connection safely (ARCHITECTURE.md §8, §10): URL checks, signing keys, a TCP connect that
cannot block start-up, socket errors that reach the caller instead of being printed and swallowed.

pymavlink is imported lazily (``load_mavutil``) after ``MAVLINK20=1`` is set, because it picks MAVLink 1 or
2 when it is first imported and the LANDING_TARGET extension fields exist only in MAVLink 2.
"""
from __future__ import annotations

import fcntl
import os
import socket
import struct
import termios
from pathlib import Path
from typing import Any, Callable

from edge_landing.runtime.core.errors import InputError

NET_PREFIXES = ("udpout:", "udpin:", "udp:", "udpbcast:", "tcp:", "tcpin:")
UDP_PREFIXES = ("udpout:", "udpin:", "udp:", "udpbcast:")


def load_mavutil() -> Any:
    """pymavlink's mavutil with the MAVLink 2 dialect, whatever was imported before."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
        mavutil.set_dialect("ardupilotmega")  # pymavlink was imported earlier without MAVLINK20
    return mavutil


def check_url(url: str) -> None:
    """Fail fast on a connection string pymavlink would not understand."""
    if url.startswith(NET_PREFIXES):
        host_port = url.split(":", 1)[1]
        host, _, port = host_port.rpartition(":")
        if not host or not port.isdigit():
            raise InputError(f"MAVLink connection '{url}' needs host:port after the scheme, e.g. udpout:127.0.0.1:14550")
        if not 0 < int(port) < 65536:
            raise InputError(f"MAVLink connection '{url}': port {port} is not in 1-65535")
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


def open_connection(mavutil: Any, url: str, source_system: int, source_component: int,
                    connect_timeout_s: float) -> Any:
    """A pymavlink connection whose socket errors raise. Raises OSError (or pymavlink's errors) on failure.

    TCP connects with a timeout: pymavlink's own connect blocks until the kernel gives up (~130 s against an
    endpoint that drops SYNs).
    """
    kwargs = dict(source_system=source_system, source_component=source_component)
    if url.startswith("tcp:"):
        conn = _timed_tcp(mavutil, url[4:], connect_timeout_s, **kwargs)
    elif not url.startswith(NET_PREFIXES) and "," in url:
        conn = mavutil.mavlink_connection(url.split(",", 1)[0], baud=int(url.split(",", 1)[1]), **kwargs)
    else:
        conn = mavutil.mavlink_connection(url, **kwargs)
    try:
        if url.startswith("udpout:"):
            # A connected UDP socket reports 'port unreachable' as ConnectionRefusedError on the next send or
            # receive; pymavlink's receive swallows it, so ours lets it through.
            conn.port.connect(conn.destination_addr)
            conn.recv = _strict_udp_recv(conn.port)
    except OSError:  # e.g. the host name does not resolve (yet): retried like a refused connection
        conn.close()
        raise
    if url.startswith(("udpout:", "tcp:")):
        conn.mav.file = _RaisingWriter(conn.port)  # pymavlink's own write swallows socket errors
    if url.startswith("tcp:"):
        # pymavlink only prints on a closed TCP peer (and keeps printing); raise so we reconnect.
        conn.handle_eof = conn.handle_disconnect = _raise_closed
    return conn


def _timed_tcp(mavutil: Any, host_port: str, timeout_s: float, **kwargs: Any) -> Any:
    class TimedTcp(mavutil.mavtcp):  # type: ignore[misc]
        def do_connect(self) -> None:
            self.port = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self.port.settimeout(timeout_s)
            try:
                self.port.connect(self.destination_addr)
            except OSError:
                self.port.close()
                raise
            self.port.setblocking(False)
            self.port.setsockopt(socket.SOL_TCP, socket.TCP_NODELAY, 1)

    return TimedTcp(host_port, retries=0, **kwargs)


def unsent_bytes(sock: socket.socket) -> int:
    """Bytes still in a TCP socket's send queue (Linux SIOCOUTQ), 0 where that cannot be asked."""
    try:
        buf = fcntl.ioctl(sock.fileno(), termios.TIOCOUTQ, b"\0\0\0\0")
        return int(struct.unpack("i", buf)[0])
    except (OSError, ValueError):
        return 0


class _RaisingWriter:
    """Stands in for pymavlink's file object so that socket errors reach us instead of being swallowed."""

    def __init__(self, sock: socket.socket):
        self.sock = sock

    def write(self, buf: bytes) -> None:
        self.sock.send(buf)


def _strict_udp_recv(sock: socket.socket) -> Callable[..., bytes]:
    def recv(n: object = None) -> bytes:
        try:
            return sock.recv(65535)
        except BlockingIOError:
            return b""
    return recv


def _raise_closed() -> None:
    raise ConnectionResetError("connection closed by the other end")
