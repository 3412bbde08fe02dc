"""The MAVLink link (ARCHITECTURE.md §8, §12): heartbeat, LANDING_TARGET, STATUSTEXT out; telemetry in; signing.

Trust: telemetry is taken from one autopilot only (the sender of the first autopilot-type HEARTBEAT, or the
system named by ``LinkConfig.target_system``); other senders are counted and ignored. The link is "up" only
while that autopilot is heard; a target is sent only then, only while it is younger than
``max_target_age_s``, and (TCP) only while the socket is not backed up, so nothing stale is queued for later.
A dead link never stops the pipeline: errors are caught and counted, logged once per state change, the
connection is (re)opened with back-off in the link's own thread (start-up never blocks on it), and sending
resumes when the other end returns. Example::

    link = MavlinkLink(LinkConfig("udpout:127.0.0.1:14550"), TelemetryBuffer()).start()
    sent, why = link.send_target(target, state)      # never raises
    link.stop()
"""
from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any, Dict, Optional, Tuple

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import Target, VehicleState
from edge_landing.runtime.io.autopilot_peer import AutopilotPeer
from edge_landing.runtime.io.autopilot_setup import AutopilotSetup, SetupCheck, SetupConfig
from edge_landing.runtime.io.link_config import Autopilot, LinkConfig, LinkCounts
from edge_landing.runtime.io.mavlink_conn import (  # noqa: F401  (re-exported: the link's public helpers)
    NET_PREFIXES,
    UDP_PREFIXES,
    check_url,
    load_mavutil,
    load_signing_key,
    open_connection,
    unsent_bytes,
)
from edge_landing.runtime.io.send_rate import SendRate
from edge_landing.runtime.io.setup_reader import SetupReader
from edge_landing.runtime.io.status_text import StatusSender
from edge_landing.runtime.io.stream_requests import StreamRequests
from edge_landing.runtime.io.target_message import (  # noqa: F401  (the frames re-exported)
    FRAME_BODY_FRD,
    FRAME_LOCAL_NED,
    TargetStamps,
    body_vector,
    landing_target_message,
    message_vector,
)
from edge_landing.runtime.io.telemetry import TelemetryBuffer
from edge_landing.runtime.io.telemetry_feed import (  # noqa: F401  (TELEMETRY_MESSAGES re-exported)
    ESTIMATOR_MESSAGES,
    GIMBAL_MESSAGE,
    TELEMETRY_MESSAGES,
    feed_gimbal_report,
    feed_telemetry,
)
from edge_landing.runtime.io.timesync_client import TimesyncClient
from edge_landing.runtime.io.tlog import TlogWriter

__all__ = ["Autopilot", "LinkConfig", "LinkCounts", "MavlinkLink", "check_url", "load_mavutil", "load_signing_key",
           "NET_PREFIXES", "FRAME_BODY_FRD", "FRAME_LOCAL_NED", "TELEMETRY_MESSAGES"]
log = logging.getLogger(__name__)


class MavlinkLink:
    """A MAVLink connection with its own receive/heartbeat thread; the send methods never raise."""

    def __init__(self, config: LinkConfig, telemetry: TelemetryBuffer):
        self.config = config
        self.telemetry = telemetry
        self.counts = LinkCounts()
        self._peer = AutopilotPeer(config, lambda text, severity: self.send_status(text, severity))
        self._conn: Any = None
        self._mavutil: Any = None
        self._key: Optional[bytes] = None
        self._lock = threading.Lock()
        self._status: Optional[StatusSender] = None          # set by start, with pymavlink loaded
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._last_error_s = -math.inf
        self._last_error = ""
        self._last_heard_s = -math.inf
        self._up_reported: Optional[bool] = None
        self._skip_reported = False
        self._stamps = TargetStamps()                        # LANDING_TARGET time_usec, always a later millisecond
        # The estimator's status at 2 Hz (each autopilot refuses the other's message id: harmless).
        wanted = {**{name: config.telemetry_rate_hz for name in TELEMETRY_MESSAGES}, **{n: 2.0 for n in ESTIMATOR_MESSAGES}}
        if telemetry.gimbal is not None:
            wanted[GIMBAL_MESSAGE] = config.telemetry_rate_hz
        self._streams = StreamRequests(wanted)
        self._last_request_s = -math.inf
        self._timesync: Optional[TimesyncClient] = None
        self._noise_seen = 0
        self._target_rate = SendRate(config.max_target_hz)
        self._tlog: Optional[TlogWriter] = None
        # ArduPilot's precision-landing parameters (autopilot_setup.py); PX4's are not read.
        check = config.setup_check if config.autopilot is Autopilot.ARDUPILOT else SetupCheck.OFF
        self.setup = AutopilotSetup(SetupConfig(check)) if check is not SetupCheck.OFF else None
        self._setup_reader: Optional[SetupReader] = None

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
        self._status = StatusSender(self._send, self._mavutil.mavlink)
        self._timesync = TimesyncClient(self.telemetry, self.counts, self._send, self._mavutil.mavlink)
        if self.setup is not None:
            self._setup_reader = SetupReader(self.setup, self._send, self.send_status, self._mavutil.mavlink)
        if self.config.tlog_out:
            self._tlog = TlogWriter(self.config.tlog_out)
        # Connecting happens in the thread: an endpoint that drops connection attempts never blocks start-up.
        self._thread = threading.Thread(target=self._run, name="mavlink", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=3.0)
        if self._tlog is not None:
            self._tlog.close()
        with self._lock:
            self._close()

    def counters(self) -> Dict[str, int]:
        """A snapshot of the link's counters."""
        return self.counts.snapshot()

    def setup_report(self) -> Optional[Dict[str, object]]:
        """What was read of the autopilot's precision-landing setup (None: not checked; autopilot_setup.py)."""
        return None if self.setup is None else self.setup.report()

    def heard_age_s(self, now_s: Optional[float] = None) -> float:
        """Seconds since the autopilot was last heard (inf if never)."""
        return (time.monotonic() if now_s is None else now_s) - self._last_heard_s

    @property
    def up(self) -> bool:
        """Connected, no recent error, and the autopilot heard recently."""
        now = time.monotonic()
        return (self._conn is not None and now - self._last_error_s > self.config.error_quiet_s
                and self.heard_age_s(now) <= self.config.heard_within_s)

    # -- sending (pipeline thread) ----------------------------------------------------------------------
    def send_target(self, target: Target, state: Optional[VehicleState],
                    clock_lag_s: float = 0.0, stamp_s: Optional[float] = None) -> Tuple[bool, str]:
        """Send LANDING_TARGET for a valid target; returns (sent, why not). Sent means it left the socket.
        ``clock_lag_s``: the frame's Frame.clock_lag_s (a simulated flight's clock behind this one).
        ``stamp_s``: the time the body vector holds for (the pose it was expressed at; default the capture time),
        sent as ``time_usec``. The age limit is always judged on the capture time: a re-expressed vector is no
        fresher evidence. ArduPilot takes a message as a new measurement only when its (jitter-corrected)
        millisecond differs from the last one's (AC_PrecLand::retrieve_los_meas), so a stamp not later than the
        last sent one, in milliseconds, is moved to the next millisecond (target_message.TargetStamps)."""
        body, why = body_vector(target)
        if body is None:
            return False, why
        now = time.monotonic()
        age = now - clock_lag_s - target.capture_time_s
        if age > self.config.max_target_age_s:
            self.counts.add("dropped_old_targets")
            return False, f"target too old: captured {age:.2f} s ago (limit {self.config.max_target_age_s:g} s)"
        heard = self.heard_age_s(now)
        if heard > self.config.heard_within_s:
            self.counts.add("dropped_not_heard")
            return False, ("link down: no autopilot heard yet" if heard == math.inf
                           else f"link down: autopilot not heard for {heard:.1f} s")
        recorded = self._peer.holds_recorded(now)
        if recorded:
            self.counts.add("held_recorded_armed")
            return False, recorded
        xyz, frame = message_vector(target, body, state, self.config.autopilot)
        if xyz is None:
            self.counts.add("skipped_px4_no_position")
            if not self._skip_reported:
                log.warning("px4 mode: no LOCAL_POSITION_NED telemetry matched frame %d, so no LANDING_TARGET "
                            "is sent (PX4 needs the target's absolute local position)", target.frame_id)
                self._skip_reported = True
            return False, "px4 needs LOCAL_POSITION_NED telemetry"
        self._skip_reported = False
        held = self.setup.hold_reason(now) if self.setup is not None else ""
        if held:
            self.counts.add("held_setup")
            return False, held
        backlog = self._backlog()
        if backlog > self.config.max_unsent_bytes:
            self.counts.add("dropped_backed_up")
            return False, f"link backed up: {backlog} bytes not yet taken by the peer"
        if not self._target_rate.allow(now):
            self.counts.add("rate_capped")
            return False, f"rate cap: at most {self.config.max_target_hz:g} LANDING_TARGET/s (--target-hz)"
        stamp_us = self._stamps.next_us(target.capture_time_s if stamp_s is None else stamp_s)
        if self._send(landing_target_message(self._mavutil.mavlink, target, xyz, frame, stamp_us)):
            self.counts.add("targets")
            self._stamps.sent(stamp_us)
            return True, ""
        return False, "link down: send failed"

    def send_status(self, text: str, severity: int = 6) -> bool:
        """STATUSTEXT (severity 6 = INFO). Longer than 50 characters, it goes as MAVLink 2 chunks of one ``id``, up
        to 199 characters (io.status_text); a receiver that does not join chunks shows the first 50 first, so put
        the number first. True when every chunk was sent; stops at the first that was not."""
        if self._status is None or not self._status.send(text, severity):
            return False
        self.counts.add("statustext")
        return True

    def _backlog(self) -> int:
        """Bytes queued for the peer: a TCP socket's send queue, or a serial port's output queue (a radio slower
        than what is written builds one, and a target that waits there arrives late). UDP has no queue to ask."""
        conn = self._conn
        url = self.config.url
        if conn is None or (url.startswith(NET_PREFIXES) and not url.startswith("tcp:")):
            return 0
        return unsent_bytes(conn.port)

    def _send(self, msg: Any) -> bool:
        with self._lock:
            if self._conn is None:
                return False
            try:
                self._conn.mav.send(msg)
                return True
            except BlockingIOError:
                return False  # socket buffer full: drop this message, the link itself is fine
            except (OSError, ValueError) as exc:  # refused / reset / serial gone
                if not self.config.url.startswith(UDP_PREFIXES):
                    self._close()  # a stream connection is dead after an error: the thread reopens it
                self._fault(f"send failed: {exc}")
                return False

    # -- connection -----------------------------------------------------------------------------------
    def _connect(self) -> bool:
        c = self.config
        try:
            conn = open_connection(self._mavutil, c.url, c.system_id, c.component_id, c.connect_timeout_s)
        except Exception as exc:  # pymavlink raises OSError, serial.SerialException or bare Exception
            self._fault(f"cannot connect: {exc}")
            return False
        if self._key is not None:
            conn.setup_signing(self._key, sign_outgoing=True)
            # pymavlink drops unsigned and badly signed messages silently; this hook sees every one of them.
            conn.mav.signing.allow_unsigned_callback = self._rejected_signature
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
        self.counts.add("send_errors")
        self._last_error_s = time.monotonic()
        self._last_error = reason
        self._report()

    def _report(self) -> None:
        up = self.up
        if up != self._up_reported:
            if up:
                log.info("MAVLink link %s is up (autopilot %s heard)", self.config.url, self.peer)
            elif self._up_reported is not None:
                why = self._last_error if time.monotonic() - self._last_error_s <= self.config.error_quiet_s \
                    else f"autopilot not heard for {self.heard_age_s():.1f} s"
                log.warning("MAVLink link %s is down (%s); no targets are sent until it is back", self.config.url, why)
            self._up_reported = up

    # -- the thread -----------------------------------------------------------------------------------
    def _run(self) -> None:
        backoff_s = 0.0
        next_heartbeat_s = 0.0
        first = True
        while not self._stop.is_set():
            if self._conn is None:
                if self._stop.wait(backoff_s):
                    break
                if self._connect():
                    self.counts.add("reconnects", 0 if first else 1)
                    backoff_s = self.config.reconnect_min_s
                else:
                    backoff_s = min(max(backoff_s * 2.0, self.config.reconnect_min_s), self.config.reconnect_max_s)
                first = False
                continue
            now = time.monotonic()
            if now >= next_heartbeat_s:
                self._heartbeat()
                next_heartbeat_s = now + self.config.heartbeat_period_s
            self._request_telemetry(now)
            if self._timesync is not None and self.peer is not None:
                self._timesync.tick(now)
            if self._setup_reader is not None and self.peer is not None:
                self._setup_reader.tick(now, self.peer, self.telemetry.reboots)
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
                if self._tlog is not None and msg.get_type() != "BAD_DATA":
                    self._tlog.write(msg)
                self._handle(msg)
            self._count_noise(conn)
            self._report()

    def _count_noise(self, conn: Any) -> None:
        """Bytes that were not MAVLink packets (ResyncParser skipped them): said once, counted always."""
        skipped = int(getattr(getattr(conn.mav, "resync", None), "skipped_bytes", 0))
        new = skipped - self._noise_seen
        if new <= 0:
            self._noise_seen = min(self._noise_seen, skipped)   # a new connection counts from 0
            return
        if self.counts["noise_bytes"] == 0:
            log.warning("MAVLink %s: bytes that are not MAVLink packets are arriving (noise on the line, a wrong "
                        "baud rate, another protocol); the packets around them are still read", self.config.url)
        self._noise_seen = skipped
        self.counts.add("noise_bytes", new)

    def _rejected_signature(self, _mav: Any, _msg_id: int) -> bool:
        """Say so when signed traffic is rejected: a wrong key otherwise drops all telemetry silently."""
        if self.counts["bad_signature"] == 0:
            log.warning("MAVLink signing: messages with a bad or missing signature are arriving and are dropped "
                        "(wrong --mav-key?); no telemetry from them")
        self.counts.add("bad_signature")
        return False

    def _heartbeat(self) -> None:
        m = self._mavutil.mavlink
        if self._send(m.MAVLink_heartbeat_message(m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 0, 0,
                                                  m.MAV_STATE_ACTIVE, 3)):
            self.counts.add("heartbeats")

    def _request_telemetry(self, now: float) -> None:
        """Ask the autopilot for each stream we need while it arrives slower than asked (stream_requests.py)."""
        if self.peer is None or now - self._last_request_s < 0.5:
            return
        self._last_request_s = now
        m = self._mavutil.mavlink
        for name, interval_us in self._streams.due(now, self.telemetry.reboots):
            msg_id = getattr(m, f"MAVLINK_MSG_ID_{name}")
            self._send(m.MAVLink_command_long_message(self.peer[0], self.peer[1], m.MAV_CMD_SET_MESSAGE_INTERVAL,
                                                      0, msg_id, interval_us, 0, 0, 0, 0, 0))

    @property
    def peer(self) -> Optional[Tuple[int, int]]:
        """(system, component) of the autopilot, once its HEARTBEAT was heard (autopilot_peer.py)."""
        return self._peer.sender

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return
        self.counts.add("received")
        sender = (int(msg.get_srcSystem()), int(msg.get_srcComponent()))
        if kind == "HEARTBEAT":
            self._peer.consider(msg, sender)
        if self.peer is None:
            self.counts.add("before_autopilot")
            return
        if kind == GIMBAL_MESSAGE and sender[0] == self.peer[0]:   # the autopilot's or a gimbal device's
            self._streams.arrived(kind, time.monotonic())
            if feed_gimbal_report(self.telemetry, msg, sender, self.peer, time.monotonic()):
                self.counts.add("gimbal_reports")
            return
        arrival = time.monotonic()
        if kind == "HEARTBEAT":   # whether the vehicle is armed, known before the autopilot counts as heard
            self._peer.heartbeat(msg, sender, arrival)
        if sender != self.peer:
            self.counts.add("other_senders")
            return
        self._last_heard_s = arrival
        if kind == "HEARTBEAT":
            return
        if kind == "TIMESYNC":
            if self._timesync is not None:
                self._timesync.on_message(msg, arrival)
            return
        if kind == "PARAM_VALUE" and self._setup_reader is not None:
            self._setup_reader.on_param_value(msg)
            return
        if feed_telemetry(self.telemetry, msg, arrival, self._mavutil.mavlink):
            self._streams.arrived(kind, arrival)

