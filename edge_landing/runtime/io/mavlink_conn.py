"""Opening a pymavlink connection safely (ARCHITECTURE.md §8, §10): URL checks, signing keys, a TCP connect that
cannot block start-up, socket errors that reach the caller instead of being printed and swallowed, and a parser
that finds real packets again after garbage bytes (``ResyncParser``).

pymavlink is imported lazily (``load_mavutil``) after ``MAVLINK20=1`` is set, because it picks MAVLink 1 or
2 when it is first imported and the LANDING_TARGET extension fields exist only in MAVLink 2.
"""
from __future__ import annotations

import fcntl
import os
import socket
import struct
import sys
import termios
from pathlib import Path
from typing import Any, Callable, Dict

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
    ResyncParser(conn.mav).install()
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


def unsent_bytes(port: Any) -> int:
    """Bytes still in a TCP socket's send queue or a serial port's output queue (Linux SIOCOUTQ / TIOCOUTQ, the
    same request), 0 where that cannot be asked (a pseudo-terminal always says 0)."""
    try:
        buf = fcntl.ioctl(port.fileno(), termios.TIOCOUTQ, b"\0\0\0\0")
        return int(struct.unpack("i", buf)[0])
    except (OSError, ValueError):
        return 0


class ResyncParser:
    """Takes over framing from a pymavlink ``MAVLink`` object so that garbage cannot hide real packets.

    pymavlink trusts the length byte after any 0xFD/0xFE it meets: on a noisy line a false start marker makes
    it swallow up to 280 following bytes as one "packet" and throw them all away when that fails its CRC (or,
    with an unknown message id, hand them on unchecked), so the real packets inside are lost, and it often
    lands inside the next real packet, so the loss cascades. Here a candidate frame is taken only when its
    message id is known and pymavlink's own ``decode`` accepts it (CRC, signature); otherwise the search goes on
    from the byte after the false marker. A frame whose CRC holds but that ``decode`` refuses (a bad or
    missing signature: counted by the signing callback there) is real and is skipped up to its CRC. A message
    id this dialect does not know has no CRC to check, so it is never taken as a packet (pymavlink would hand
    it on as ``UNKNOWN_<id>``).

    ``parse_char`` and ``bytes_needed`` replace the object's own (pymavlink's ``recv_msg`` and ``parse_buffer``
    call them); they never raise, and the buffer holds at most ``MAX_BUFFERED`` bytes (the oldest go).
    """

    MAX_BUFFERED = 1 << 18

    def __init__(self, mav: Any):
        self.mav = mav
        dialect = sys.modules[type(mav).__module__]
        self._map: Dict[int, Any] = dialect.mavlink_map
        self._crc = dialect.x25crc
        self._buf = bytearray()
        self._need = 1
        self.skipped_bytes = 0   # bytes that were not part of a packet taken or a real one refused
        self.false_starts = 0    # start markers that began no packet

    def install(self) -> ResyncParser:
        self.mav.parse_char = self.parse_char
        self.mav.bytes_needed = self.bytes_needed
        self.mav.resync = self
        return self

    def bytes_needed(self) -> int:
        return self._need

    def parse_char(self, data: Any) -> Any:
        """Add bytes; return the next message, or None until one is complete."""
        buf, mav = self._buf, self.mav
        if data:
            buf.extend(data)
            mav.total_bytes_received += len(data)
            if len(buf) > self.MAX_BUFFERED:
                self._skip(len(buf) - self.MAX_BUFFERED)
        while True:
            start = buf.find(0xFD)
            v1 = buf.find(0xFE, 0, start if start >= 0 else len(buf))
            start = v1 if v1 >= 0 else start
            if start < 0:
                self._skip(len(buf))
                self._need = 8
                return None
            if start:
                self._skip(start)
            if buf[0] == 0xFD:
                header = 10
                if len(buf) < header:
                    self._need = header - len(buf)
                    return None
                flags = buf[2]
                msg_id = buf[7] | buf[8] << 8 | buf[9] << 16
                size = header + buf[1] + 2 + (13 if flags & 1 else 0)
                plausible = flags & ~1 == 0 and msg_id in self._map
            else:
                header, flags = 6, 0
                if len(buf) < header:
                    self._need = header - len(buf)
                    return None
                msg_id, length = buf[5], buf[1]
                size = header + length + 2
                # MAVLink 1 never truncates a payload nor carries more than the message has: a false 0xFE
                # claiming more is dropped at once instead of holding the packets behind it until its CRC.
                plausible = msg_id in self._map and length <= self._map[msg_id].unpacker.size
            if not plausible:
                self._false_start()
                continue
            if len(buf) < size:
                self._need = size - len(buf)
                return None
            frame = buf[:size]
            # pymavlink stores a signed stream's time stamp before it compares the signature: a frame that fails
            # would otherwise leave its (perhaps garbage) time stamp behind, and every later real packet of that
            # stream would be refused as a replay.
            stream = (frame[-13], frame[5], frame[6]) if header == 10 and flags & 1 else None
            stamp = mav.signing.stream_timestamps.get(stream) if stream else None
            try:
                msg = mav.decode(frame)
            except Exception:  # pymavlink's MAVError (CRC, signature, payload) or anything else it raises
                mav.total_receive_errors += 1
                if stream:
                    if stamp is None:
                        mav.signing.stream_timestamps.pop(stream, None)
                    else:
                        mav.signing.stream_timestamps[stream] = stamp
                if self._crc_holds(frame, header, msg_id):
                    # A real packet refused (its signature): none of its bytes starts a packet. The signature
                    # block is not covered by the CRC (it may be the next packet after a cut-off one): rescanned.
                    self._skip(header + frame[1] + 2)
                else:
                    self._false_start()
                continue
            del buf[:size]
            self._need = 1 if buf else 8
            mav.total_packets_received += 1
            if mav.callback is not None:
                mav.callback(msg, *(mav.callback_args or ()), **(mav.callback_kwargs or {}))
            return msg

    def _skip(self, n: int) -> None:
        del self._buf[:n]
        self.skipped_bytes += n

    def _false_start(self) -> None:
        self.false_starts += 1
        self._skip(1)

    def _crc_holds(self, frame: bytearray, header: int, msg_id: int) -> bool:
        end = header + frame[1]
        crc = self._crc(frame[1:end])
        crc.accumulate(bytes([self._map[msg_id].crc_extra]))
        return bool(crc.crc == frame[end] | frame[end + 1] << 8)


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
