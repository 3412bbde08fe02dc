"""A scriptable fake autopilot for the trust tests: a TEST DOUBLE (a real autopilot cannot be installed here).

Real pymavlink on both ends over loopback UDP (or TCP): it listens on ``udpin:127.0.0.1:PORT`` (or
``tcpin:``), records every message edge-run sends with its arrival time, and, once edge-run is heard, calls
``script(fake, t_s)`` every tick (``t_s`` = seconds since edge-run was first heard). The script decides what
to send; :meth:`healthy` sends what a well-behaved ArduPilot would (HEARTBEAT, ATTITUDE, LOCAL_POSITION_NED,
GLOBAL_POSITION_INT), with ``time_boot_ms`` from this fake's own clock. Like ArduPilot (GCS_Common.cpp,
handle_timesync) it answers a TIMESYNC request with ``tc1`` = that clock at the request's arrival, in ns, and
``ts1`` echoed; ``timesync`` = False makes it ignore them, ``timesync_delay_s`` holds each answer back.
Like ArduPilot (GCS_Param.cpp; benchmarks.autopilot_params) it answers PARAM_REQUEST_READ by name from
``params`` (a precision-landing setup that is right, by default); ``params = None`` ignores the requests.
``set_param`` broadcasts the new value as ArduPilot does after a set; ``reboot`` restarts its boot clock.
"""
from __future__ import annotations

import math
import threading
import time
from typing import Any, Callable, Dict, List, Optional, Tuple

from edge_landing.benchmarks.autopilot_params import PRECLAND_PARAMS, answer_param_request, send_param
from edge_landing.runtime.io.mavlink_conn import load_mavutil

__all__ = ["FakeAutopilot", "PRECLAND_PARAMS", "answer_param_request"]

Script = Callable[["FakeAutopilot", float], None]


class FakeAutopilot:
    def __init__(self, port: int, script: Script, rate_hz: float = 30.0, tcp: bool = False, sysid: int = 1):
        self.mavutil = load_mavutil()
        url = f"{'tcpin' if tcp else 'udpin'}:127.0.0.1:{port}"
        self.conn = self.mavutil.mavlink_connection(url, source_system=sysid, source_component=1)
        self.script, self.rate_hz, self.tcp = script, rate_hz, tcp
        self.messages: List[Tuple[float, object]] = []   # (arrival monotonic s, message)
        self.heard_s: Optional[float] = None             # monotonic time edge-run was first heard
        self.read = True                                 # False: stop reading (a stuck peer)
        self.errors: List[str] = []
        self.clock_rate = 1.0                            # boot clock speed against real time
        self.timesync = True                             # answer TIMESYNC requests (ArduPilot and PX4 do)
        self.timesync_delay_s = 0.0
        self._answers: List[Tuple[float, int, int]] = []  # (due monotonic s, tc1 ns, ts1)
        self.params: Optional[Dict[str, float]] = dict(PRECLAND_PARAMS)   # None: PARAM_REQUEST_READ is ignored
        self.armed = False                               # what healthy()'s HEARTBEAT says
        self._param_answers: List[str] = []
        self._t0 = time.monotonic()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> FakeAutopilot:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=3)
        self.conn.close()

    # -- what edge-run sent ---------------------------------------------------------------------------
    def of_type(self, kind: str) -> List[Tuple[float, object]]:
        return [(t, m) for t, m in list(self.messages) if m.get_type() == kind]

    def targets_between(self, t0_s: float, t1_s: float) -> list:
        """LANDING_TARGETs that arrived between two script times (seconds since edge-run was heard)."""
        if self.heard_s is None:
            return []
        return [m for t, m in self.of_type("LANDING_TARGET") if t0_s <= t - self.heard_s < t1_s]

    def texts(self) -> List[str]:
        return [m.text for _, m in self.of_type("STATUSTEXT")]

    # -- what the script can send ---------------------------------------------------------------------
    def boot_ms(self, clock_rate: Optional[float] = None, offset_ms: float = 0.0) -> int:
        rate = self.clock_rate if clock_rate is None else clock_rate
        return int((time.monotonic() - self._t0) * 1000 * rate + offset_ms) + 1

    def _on_timesync(self, msg: Any, now: float) -> None:
        if self.timesync and msg.tc1 == 0:
            tc1_ns = int((now - self._t0) * 1e9 * self.clock_rate) + 1_000_000
            self._answers.append((now + self.timesync_delay_s, tc1_ns, int(msg.ts1)))

    def set_param(self, name: str, value: float) -> None:
        """A parameter set (from a ground station): stored and broadcast, as ArduPilot does."""
        assert self.params is not None
        self.params[name] = value
        self._param_answers.append(name)

    def reboot(self) -> None:
        """The boot clock starts again (parameters are kept, as ArduPilot keeps them in storage)."""
        self._t0 = time.monotonic()

    def _on_param_request(self, msg: Any) -> None:
        name = str(msg.param_id).rstrip("\x00")
        if self.params is not None and name in self.params:
            self._param_answers.append(name)

    def _send_answers(self, now: float) -> None:
        names, self._param_answers = self._param_answers, []
        for name in names if self.params is not None else []:
            send_param(self.conn.mav, name, self.params)
        due = [a for a in self._answers if a[0] <= now]
        self._answers = [a for a in self._answers if a[0] > now]
        for _, tc1, ts1 in due:
            self.conn.mav.timesync_send(tc1, ts1)

    def healthy(self, boot_ms: Optional[int] = None, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0,
                ned: Tuple[float, float, float] = (5.0, -3.0, -10.0), rel_alt_m: Optional[float] = None,
                mav: object = None, vel: Tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        m = self.mavutil.mavlink
        mav = mav or self.conn.mav
        ms = self.boot_ms() if boot_ms is None else boot_ms
        rel = -ned[2] if rel_alt_m is None else rel_alt_m
        base_mode = m.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0
        mav.heartbeat_send(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, base_mode, 0, m.MAV_STATE_ACTIVE)
        mav.attitude_send(ms, roll, pitch, yaw, 0.0, 0.0, 0.0)
        mav.local_position_ned_send(ms, *ned, *vel)
        mav.global_position_int_send(ms, 0, 0, 0, int(rel * 1000) if math.isfinite(rel) else 0, 0, 0, 0, 0)

    def _run(self) -> None:
        next_tick = 0.0
        while not self._stop.is_set():
            if self.read or not self.tcp:
                msg = self.conn.recv_match(blocking=True, timeout=0.005)
                if msg is not None and msg.get_type() != "BAD_DATA":
                    now = time.monotonic()
                    if self.read:
                        self.messages.append((now, msg))
                    if self.heard_s is None:
                        self.heard_s = now
                    if msg.get_type() == "TIMESYNC":
                        self._on_timesync(msg, now)
                    elif msg.get_type() == "PARAM_REQUEST_READ":
                        self._on_param_request(msg)
            else:
                time.sleep(0.005)
            now = time.monotonic()
            if (self._answers or self._param_answers) and self._connected():
                try:
                    self._send_answers(now)
                except Exception as exc:  # a send into a closed socket: note it, keep the fake alive
                    self.errors.append(str(exc))
            if self.heard_s is not None and now >= next_tick and self._connected():
                next_tick = now + 1.0 / self.rate_hz
                try:
                    self.script(self, now - self.heard_s)
                except Exception as exc:  # a send into a closed socket: note it, keep the fake alive
                    self.errors.append(str(exc))

    def _connected(self) -> bool:
        return bool(self.conn.port is not None) if self.tcp else bool(self.conn.clients)
