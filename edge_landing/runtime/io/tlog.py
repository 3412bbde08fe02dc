"""A recorded flight replayed with its own MAVLink telemetry log (``edge-run --tlog``, ARCHITECTURE.md §4, §12).

A ground station (QGroundControl, Mission Planner, MAVProxy) or a router (mavlink-router) records what the
autopilot sent as a ``.tlog``: every packet after its arrival time, 8 bytes, big-endian microseconds since
1970 (UTC). Replayed beside the video the drone's camera recorded in the same flight, the log's ATTITUDE,
LOCAL_POSITION_NED, GLOBAL_POSITION_INT, DISTANCE_SENSOR and estimator status enter the runtime's
TelemetryBuffer exactly as the live link's do (``telemetry_feed``): the autopilot's clock is mapped from
the log's arrival times, and every trust rule (freshness, plausibility, the estimator's word, resets) applies.

Time: the user says when the video's first frame was taken on the log's clock (``video_start``); frame k
was taken ``pts_k`` later (the video's own time stamps, or k / fps). When a frame is stamped on the
grabber's clock, the log is read up to that frame's time plus ``lookahead_s``, which stands for the
pipeline's own delay: in flight, telemetry that arrives while a frame is being inferred is in hand when
it is fused. The log is read forward once, a packet at a time (memory does not grow with its length).
"""
from __future__ import annotations

import logging
import math
import os
import struct
import time
from dataclasses import dataclass
from datetime import datetime
from typing import Any, Optional, Tuple

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.io.flight_record import unix_time
from edge_landing.runtime.io.mavlink_conn import load_mavutil
from edge_landing.runtime.io.telemetry import TelemetryBuffer
from edge_landing.runtime.io.telemetry_feed import (
    GIMBAL_MESSAGE,
    feed_gimbal_report,
    feed_telemetry,
    is_autopilot_heartbeat,
)

__all__ = ["TlogConfig", "TlogTelemetry", "TlogWriter", "parse_video_start"]
log = logging.getLogger(__name__)

START_FORMS = "UNIX seconds (1732406400.25), an ISO 8601 time with its zone (2026-11-24T10:00:03.2Z), or +S " \
              "(seconds after the log's first packet)"
CLOCK_STEP_S = 1.0      # arrival times that go back further than this: the recorder's clock was stepped
AUTOPILOT_LOG_SUFFIXES = (".bin", ".log", ".px4log", ".ulg")   # pymavlink would read these as dataflash logs
_PLAUSIBLE_UNIX_S = (946684800.0, 4102444800.0)   # 2000-01-01 .. 2100-01-01: a tlog's arrival clock is UTC


@dataclass(frozen=True)
class TlogConfig:
    path: str
    video_start: str                 # when the video's first frame was taken, on the log's clock (START_FORMS)
    lookahead_s: float = 0.1         # telemetry arriving this long after a frame's capture is in hand for it
    target_system: Optional[int] = None   # the autopilot's system id when the log holds several vehicles


def parse_video_start(text: str, first_packet_unix_s: float) -> float:
    """``--tlog-video-start`` as UNIX seconds; InputError naming the value when it is none of START_FORMS."""
    raw = text.strip()
    try:
        if raw.startswith("+"):
            value = first_packet_unix_s + float(raw[1:])
        elif any(c in raw for c in "T:-") and not _is_number(raw):
            when = datetime.fromisoformat(raw.replace("Z", "+00:00"))
            if when.tzinfo is None:
                raise InputError(f"--tlog-video-start {text!r} has no time zone (add Z or +HH:MM): the log's "
                                 f"clock is UTC")
            value = when.timestamp()
        else:
            value = float(raw)
    except ValueError:
        raise InputError(f"--tlog-video-start {text!r} is not a time: expected {START_FORMS}") from None
    if not math.isfinite(value) or not _PLAUSIBLE_UNIX_S[0] <= value <= _PLAUSIBLE_UNIX_S[1]:
        raise InputError(f"--tlog-video-start {text!r} is not a time between 2000 and 2100: expected {START_FORMS}")
    return value


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


class TlogTelemetry:
    """The log's packets, read forward in arrival order; the autopilot is named by its first HEARTBEAT."""

    def __init__(self, config: TlogConfig):
        if not os.path.isfile(config.path):
            raise InputError(f"--tlog {config.path} does not exist; expected a MAVLink telemetry log (.tlog) "
                             f"recorded by a ground station or a router")
        if os.path.splitext(config.path)[1].lower() in AUTOPILOT_LOG_SUFFIXES:
            raise InputError(f"--tlog {config.path}: a dataflash or ULog file is the autopilot's own record, not a "
                             f"telemetry log; give the .tlog a ground station or router recorded")
        self.config = config
        self._mavutil = load_mavutil()
        try:
            # notimestamps=False: the 8-byte arrival time before each packet (the .tlog format).
            self._conn = self._mavutil.mavlink_connection(config.path, notimestamps=False)
        except Exception as exc:   # pymavlink raises bare Exceptions on files it cannot parse
            raise InputError(f"--tlog {config.path} cannot be read as a telemetry log ({exc})") from None
        self.peer: Optional[Tuple[int, int]] = None
        self.counts = {"packets": 0, "fed": 0, "gimbal_reports": 0, "before_autopilot": 0, "other_senders": 0}
        self.ended = False
        self._last_unix_s, self._step_said = -math.inf, False
        try:
            self._pending = self._first_packet()
            self.first_unix_s = float(self._pending._timestamp)
            self.video_start_unix_s = parse_video_start(config.video_start, self.first_unix_s)
        except InputError:
            self.close()
            raise
        if self.video_start_unix_s < self.first_unix_s - 60.0:
            log.warning("--tlog-video-start is %.0f s before the log's first packet: frames before it have no "
                        "telemetry (wrong time zone or offset?)", self.first_unix_s - self.video_start_unix_s)

    def _first_packet(self) -> Any:
        path = self.config.path
        if not isinstance(self._conn, self._mavutil.mavlogfile):
            raise InputError(f"--tlog {path} is not read as a telemetry log by pymavlink; give a .tlog")
        first = self._next()
        if first is None:
            raise InputError(f"--tlog {path} holds no MAVLink packet with a time stamp: not a .tlog "
                             f"(a dataflash .bin log or a raw capture is not read)")
        if not _PLAUSIBLE_UNIX_S[0] <= float(first._timestamp) <= _PLAUSIBLE_UNIX_S[1]:
            raise InputError(f"--tlog {path}: its first packet's time stamp ({float(first._timestamp):.0f} s) is "
                             f"not a date between 2000 and 2100: not a .tlog (a raw capture has no time stamps)")
        return first

    def _next(self) -> Any:
        """The next packet with an arrival time, or None at the end (a read fault ends the log, said once)."""
        while True:
            try:
                msg = self._conn.recv_msg()
            except Exception as exc:   # a truncated or corrupt tail must not stop the replay
                log.warning("--tlog %s: reading stopped (%s); later frames have no telemetry", self.config.path, exc)
                return None
            if msg is None:
                return None
            if msg.get_type() != "BAD_DATA" and math.isfinite(float(getattr(msg, "_timestamp", math.nan))):
                return msg

    def feed_until(self, telemetry: TelemetryBuffer, until_unix_s: float, local_offset_s: float) -> int:
        """Hand ``telemetry`` every packet that arrived up to ``until_unix_s``; a packet's local arrival time is
        its log time + ``local_offset_s``. Returns how many were the autopilot's telemetry."""
        fed = 0
        while self._pending is not None and float(self._pending._timestamp) <= until_unix_s:
            msg, self._pending = self._pending, self._next()
            self.counts["packets"] += 1
            self._check_clock(float(msg._timestamp))
            fed += self._handle(telemetry, msg, float(msg._timestamp) + local_offset_s)
        if self._pending is None and not self.ended:
            self.ended = True
            if self.peer is None:
                log.warning("--tlog %s: no autopilot HEARTBEAT in the log, so none of it was read as telemetry",
                            self.config.path)
            log.info("--tlog %s: the log ended (%d packets, %d of them the autopilot's telemetry); later frames have "
                     "no telemetry", self.config.path, self.counts["packets"], self.counts["fed"])
        return fed

    def _check_clock(self, unix_s: float) -> None:
        """Said once: a log whose arrival clock went back (a ground station's wall clock stepped in flight). The
        packets after the step are read as they come; their arrival times no longer match the frames'."""
        if unix_s < self._last_unix_s - CLOCK_STEP_S and not self._step_said:
            self._step_said = True
            log.warning("--tlog %s: the log's clock went back %.1f s at packet %d (the recorder's wall clock was set "
                        "in flight?); telemetry after it is mistimed against the video", self.config.path,
                        self._last_unix_s - unix_s, self.counts["packets"])
        self._last_unix_s = max(self._last_unix_s, unix_s)

    def _handle(self, telemetry: TelemetryBuffer, msg: Any, arrival_s: float) -> int:
        sender = (int(msg.get_srcSystem()), int(msg.get_srcComponent()))
        if self.peer is None and is_autopilot_heartbeat(msg) and self.config.target_system in (None, sender[0]):
            self.peer = sender
            log.info("--tlog: the autopilot is system %d component %d; packets from other senders are ignored",
                     *sender)
        if self.peer is None:
            self.counts["before_autopilot"] += 1
            return 0
        if msg.get_type() == GIMBAL_MESSAGE and sender[0] == self.peer[0]:   # its own report or its gimbal's
            self.counts["gimbal_reports"] += feed_gimbal_report(telemetry, msg, sender, self.peer, arrival_s)
            return 0
        if sender != self.peer:
            self.counts["other_senders"] += 1
            return 0
        # TIMESYNC in a log answers the ground station's requests, not ours: the log's arrival times stand in.
        kind = feed_telemetry(telemetry, msg, arrival_s, self._mavutil.mavlink)
        self.counts["fed"] += kind == "telemetry"
        return int(kind == "telemetry")

    def close(self) -> None:
        try:
            self._conn.close()
        except Exception:   # closing a read-only file cannot lose anything
            pass


class TlogWriter:
    """Writes what a link receives as a .tlog (edge-run --flight-record): each packet's bytes as they arrived, after
    its arrival time on the UNIX clock (8 bytes, big-endian µs; ``flight_record.unix_time``, as the frames' times).
    Written from the link's thread only; buffered, and every packet written is on disk once ``close`` returns."""

    def __init__(self, path: str):
        self.path = path
        self._file: Optional[Any] = open(path, "ab")
        self.packets = 0

    def write(self, msg: Any, arrival_unix_s: Optional[float] = None) -> None:
        """Never raises: a write that fails (a full disk) ends the recording, said once; the link goes on."""
        raw = msg.get_msgbuf()
        if not raw or self._file is None:
            return
        now = unix_time(time.monotonic()) if arrival_unix_s is None else arrival_unix_s
        try:
            self._file.write(struct.pack(">Q", int(now * 1e6)) + bytes(raw))
        except (OSError, ValueError) as exc:
            log.warning("telemetry log %s: writing failed (%s); recording stopped", self.path, exc)
            self.close()
            return
        self.packets += 1

    def close(self) -> None:
        if self._file is not None:
            file, self._file = self._file, None
            try:
                file.close()
            except OSError as exc:
                log.warning("telemetry log %s: closing failed (%s)", self.path, exc)
