"""Probe ``edge-run`` as a new user would, against a misbehaving autopilot (ARCHITECTURE.md §12). Not in CI.

Independent of the runtime's trust code: ``edge-run`` runs as a subprocess (its own command line), and the
autopilot is played here with bare pymavlink (a TEST DOUBLE). Each probe sends healthy telemetry for a few
seconds, then misbehaves. Checked per probe: edge-run exits 0 without a traceback, the healthy phase got
targets, and no LANDING_TARGET arrives later than 1 s after the last good telemetry sample (for probes whose
later samples are good but useless, e.g. an unknown height, only the committed spot may continue)::

    python -m edge_landing.benchmarks.probe_autopilot              # all probes, ~2 minutes
    python -m edge_landing.benchmarks.probe_autopilot --only silent,nan

The "late-link" probe answers TIMESYNC as ArduPilot does (the others do not, as an autopilot that ignores it)
and delivers its telemetry 1.5 s late from the end of the healthy phase. Every probe answers PARAM_REQUEST_READ
with a right precision-landing setup; in "setup-changed" a ground station sets PLND_ORIENT to 0 mid-flight.
"""
from __future__ import annotations

import argparse
import math
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

from edge_landing.benchmarks.autopilot_params import PRECLAND_PARAMS, answer_param_request, send_param

HEALTHY_S = 4.0
BAD_S = 4.0
BOUND_S = 1.0
AGL_M = 10.0


@dataclass
class Peer:
    """The misbehaving autopilot: bare pymavlink on udpin/tcpin."""

    conn: Any
    mavlink: Any
    tcp: bool
    t0: float = field(default_factory=time.monotonic)
    heard_s: Optional[float] = None
    last_good_s: float = -math.inf
    targets: List[Tuple[float, Any]] = field(default_factory=list)
    read: bool = True
    answers_timesync: bool = False   # as ArduPilot does (tc1 = its boot clock in ns); the other probes stay silent
    late: List[Tuple[float, int]] = field(default_factory=list)   # (due, time_boot_ms) held back by the link
    params: Dict[str, float] = field(default_factory=lambda: dict(PRECLAND_PARAMS))   # answered as ArduPilot does

    def ms(self, rate: float = 1.0, offset_ms: float = 0.0) -> int:
        return int((time.monotonic() - self.t0) * 1000 * rate + offset_ms) + 1

    def healthy(self, ms: Optional[int] = None, good: bool = True, rel_alt_m: float = AGL_M) -> None:
        m, mav = self.mavlink, self.conn.mav
        ms = self.ms() if ms is None else ms
        mav.heartbeat_send(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4)
        mav.attitude_send(ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        mav.local_position_ned_send(ms, 0.0, 0.0, -AGL_M, 0.0, 0.0, 0.0)
        mav.global_position_int_send(ms, 0, 0, 0, int(rel_alt_m * 1000), 0, 0, 0, 0)
        if good:
            self.last_good_s = time.monotonic()


def _silent(p: Peer, t: float) -> None:
    pass


def _nan(p: Peer, t: float) -> None:
    v = math.nan if int(t * 10) % 2 else math.inf
    p.conn.mav.heartbeat_send(2, 3, 0, 0, 4)
    p.conn.mav.attitude_send(p.ms(), v, v, v, 0.0, 0.0, 0.0)
    p.conn.mav.distance_sensor_send(p.ms(), 20, 4000, 1000, 0, 0, 25, 0)


def _flipped(p: Peer, t: float) -> None:
    p.conn.mav.heartbeat_send(2, 3, 0, 0, 4)
    p.conn.mav.attitude_send(p.ms(), math.pi, 0.0, 1e30 if int(t * 10) % 2 else 0.0, 0.0, 0.0, 0.0)
    p.conn.mav.global_position_int_send(p.ms(), 0, 0, 0, 10000, 0, 0, 0, 0)


def _future(p: Peer, t: float) -> None:
    p.conn.mav.heartbeat_send(2, 3, 0, 0, 4)
    p.conn.mav.attitude_send(p.ms(offset_ms=5000), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # every sample 5 s ahead


def _other_vehicle(p: Peer, t: float) -> None:
    other = p.mavlink.MAVLink(p.conn, srcSystem=7, srcComponent=1)
    other.heartbeat_send(2, 3, 0, 0, 4)
    other.attitude_send(p.ms(), 0.3, 0.0, 0.0, 0.0, 0.0, 0.0)
    other.global_position_int_send(p.ms(), 0, 0, 0, 30000, 0, 0, 0, 0)


def _unknown_height(p: Peer, t: float) -> None:
    p.healthy(good=False, rel_alt_m=-3.0)  # attitude fine, height above ground impossible
    p.conn.mav.distance_sensor_send(p.ms(), 20, 4000, 65000, 0, 0, 25, 0)


def _frozen(p: Peer, t: float) -> None:
    p.read = False


def _late_link(p: Peer, t: float) -> None:
    """Every sample delivered 1.5 s after it was measured (a buffering radio); TIMESYNC answered at once."""
    now = time.monotonic()
    p.late.append((now + 1.5, p.ms()))
    while p.late and p.late[0][0] <= now:
        p.healthy(ms=p.late.pop(0)[1], good=False)


def _setup_changed(p: Peer, t: float) -> None:
    """Telemetry stays healthy, but a ground station sets PLND_ORIENT to 0 (forward): ArduPilot would turn every
    direction again, so no target may leave (ARCHITECTURE.md §12)."""
    if p.params["PLND_ORIENT"] != 0.0:
        p.params["PLND_ORIENT"] = 0.0
        send_param(p.conn.mav, "PLND_ORIENT", p.params)     # ArduPilot broadcasts a parameter that was set
    p.healthy(good=False)


PROBES: Dict[str, Tuple[Callable[[Peer, float], None], bool, bool]] = {
    # name: (bad phase, over TCP, later targets may only be the committed spot)
    "silent": (_silent, False, False),
    "nan": (_nan, False, False),
    "flipped": (_flipped, False, False),
    "future": (_future, False, False),
    "other-vehicle": (_other_vehicle, False, False),
    "unknown-height": (_unknown_height, False, True),
    "tcp-frozen": (_frozen, True, False),
    "late-link": (_late_link, False, False),
    "setup-changed": (_setup_changed, False, False),
}
ANSWERS_TIMESYNC = {"late-link"}


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _assets(folder: Path) -> Tuple[str, str]:
    import cv2
    import numpy as np

    from edge_landing.benchmarks.flat_model import flat_ground_model

    video = folder / "v.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"MJPG"), 10.0, (128, 96))
    base = np.random.default_rng(0).integers(60, 200, size=(96, 128, 3), dtype=np.uint8)
    for i in range(8):
        writer.write(np.roll(base, i, axis=1))
    writer.release()
    return str(video), str(flat_ground_model(folder / "flat.onnx", arch="flat-ground-soak", note="soak benchmark model"))


def run_probe(name: str, video: str, model: str) -> Dict[str, Any]:
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    bad, tcp, committed_only = PROBES[name]
    port = _free_port(socket.SOCK_STREAM if tcp else socket.SOCK_DGRAM)
    conn = mavutil.mavlink_connection(f"{'tcpin' if tcp else 'udpin'}:127.0.0.1:{port}", source_system=1,
                                      source_component=1)
    peer = Peer(conn, mavutil.mavlink, tcp, answers_timesync=name in ANSWERS_TIMESYNC)
    stop = threading.Event()

    def loop() -> None:
        next_s = 0.0
        while not stop.is_set():
            if peer.read:
                try:
                    msg = conn.recv_match(blocking=True, timeout=0.005)
                except Exception:  # the TCP client went away: the probe goes on
                    msg = None
                if msg is not None and msg.get_type() != "BAD_DATA":
                    now = time.monotonic()
                    peer.heard_s = peer.heard_s or now
                    if msg.get_type() == "LANDING_TARGET":
                        peer.targets.append((now, msg))
                    elif answer_param_request(conn.mav, msg, peer.params):
                        pass
                    elif msg.get_type() == "TIMESYNC" and msg.tc1 == 0 and peer.answers_timesync:
                        conn.mav.timesync_send(int((now - peer.t0) * 1e9) + 1_000_000, msg.ts1)
            else:
                time.sleep(0.005)
            now = time.monotonic()
            connected = conn.port is not None if tcp else bool(conn.clients)
            if peer.heard_s is not None and now >= next_s and connected:
                next_s = now + 1 / 30
                t = now - peer.heard_s
                try:
                    peer.healthy() if t < HEALTHY_S else bad(peer, t - HEALTHY_S)
                except Exception:
                    pass

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    url = f"tcp:127.0.0.1:{port}" if tcp else f"udpout:127.0.0.1:{port}"
    # A hovering autopilot and a shifting random texture give motion geometry nothing to confirm (§11), so the
    # network's spots are sent as the probes need (--allow-unconfirmed; they are never committed).
    proc = subprocess.run([sys.executable, "-m", "edge_landing.cli.run", "--camera", video, "--model", model, "--loop",
                           "--duration", str(HEALTHY_S + BAD_S), "--mav", url, "--allow-unconfirmed"],
                          capture_output=True, text=True, timeout=120)
    stop.set()
    thread.join(timeout=3)
    conn.close()
    heard = peer.heard_s or math.inf
    healthy = [m for t, m in peer.targets if t < heard + HEALTHY_S]
    late = [(t, m) for t, m in peer.targets if t > peer.last_good_s + BOUND_S]
    if committed_only and healthy:
        ref = (healthy[-1].x, healthy[-1].y, healthy[-1].z)
        late = [(t, m) for t, m in late if max(abs(m.x - ref[0]), abs(m.y - ref[1]), abs(m.z - ref[2])) > 0.3]
    worst = max((t - peer.last_good_s for t, _ in late), default=0.0)
    ok = proc.returncode == 0 and "Traceback" not in proc.stderr and len(healthy) >= 5 and not late
    return {"probe": name, "ok": ok, "exit": proc.returncode, "traceback": "Traceback" in proc.stderr,
            "healthy_targets": len(healthy), "targets_total": len(peer.targets), "late_targets": len(late),
            "worst_late_s": round(worst, 3)}


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m edge_landing.benchmarks.probe_autopilot",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--only", help=f"comma-separated probes of: {', '.join(PROBES)}")
    a = p.parse_args(argv)
    names = a.only.split(",") if a.only else list(PROBES)
    unknown = [n for n in names if n not in PROBES]
    if unknown:
        print(f"probe_autopilot: unknown probe(s) {unknown}; expected {', '.join(PROBES)}", file=sys.stderr)
        return 2
    failed = 0
    with tempfile.TemporaryDirectory() as tmp:
        video, model = _assets(Path(tmp))
        for name in names:
            r = run_probe(name, video, model)
            failed += not r["ok"]
            print(" ".join(f"{k}={v}" for k, v in r.items()), flush=True)
    print(f"{len(names) - failed}/{len(names)} probes passed (bar: no target later than {BOUND_S:g} s after the last "
          f"good telemetry sample, no traceback, healthy phase sends targets)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
