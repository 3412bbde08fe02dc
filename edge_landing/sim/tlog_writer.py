"""The telemetry log a ground station would have recorded during an ``edge-sim --flight`` (``flight.tlog``).

What an ArduPilot copter streams at 20 Hz (ATTITUDE, LOCAL_POSITION_NED, GLOBAL_POSITION_INT, a downward
DISTANCE_SENSOR), EKF_STATUS_REPORT at 2 Hz and HEARTBEATs at 1 Hz, plus the ground station's own heartbeat,
each packet after its arrival time (8 bytes, big-endian µs since 1970): the ``.tlog`` format. The autopilot
stamps ``time_boot_ms`` on its own clock (booted ``boot_s`` before the log starts); packets arrive 12 ms plus
a seeded jitter later. The log starts ``PREROLL_S`` before the video's first frame, with the vehicle holding
the first pose, so ``edge-run --tlog flight.tlog --tlog-video-start +2`` replays the flight.

Poses between frames are interpolated linearly (angles the short way): the same interpolation the runtime
applies, so a replay through the log matches a replay through ``poses.csv``.
"""
from __future__ import annotations

import math
import struct
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from edge_landing.runtime.io.poses import Pose

__all__ = ["write_flight_tlog", "PREROLL_S", "LOG_START_UNIX_S"]

PREROLL_S = 2.0                       # the log starts this long before the video's first frame
LOG_START_UNIX_S = 1767225600.0       # 2026-01-01T00:00:00Z: a fixed date, so a scene folder is reproducible
RATE_HZ = 20.0                        # what edge-run asks an autopilot for (SET_MESSAGE_INTERVAL)
LATENCY_S, JITTER_S = 0.012, 0.004
BOOT_S = 93.4                         # the autopilot had been up this long when the log started
RANGE_MIN_CM, RANGE_MAX_CM = 20, 13000


def _interpolate(poses: Sequence[Pose], t_s: float) -> tuple[np.ndarray, np.ndarray, float]:
    """(NED position, roll/pitch/yaw, agl) at flight time ``t_s``, held before the first and after the last."""
    times = np.array([p.t_s for p in poses])
    i = int(np.clip(np.searchsorted(times, t_s), 1, len(poses) - 1)) if len(poses) > 1 else 0
    a, b = poses[max(i - 1, 0)], poses[i]
    w = 0.0 if b.t_s == a.t_s else float(np.clip((t_s - a.t_s) / (b.t_s - a.t_s), 0.0, 1.0))
    pos = np.asarray(a.ned_m) + w * (np.asarray(b.ned_m) - np.asarray(a.ned_m))
    ang_a = np.array([a.roll_rad, a.pitch_rad, a.yaw_rad])
    delta = (np.array([b.roll_rad, b.pitch_rad, b.yaw_rad]) - ang_a + math.pi) % (2 * math.pi) - math.pi
    att = ang_a + w * delta
    att[2] = math.remainder(float(att[2]), 2 * math.pi)
    return pos, att, a.agl_m + w * (b.agl_m - a.agl_m)


def _telemetry(m: Any, poses: Sequence[Pose], t_s: float, boot_ms: int) -> list[Any]:
    pos, att, agl = _interpolate(poses, t_s)
    dt = 0.5 / RATE_HZ
    vel = (_interpolate(poses, t_s + dt)[0] - _interpolate(poses, t_s - dt)[0]) / (2 * dt)
    tilt = math.cos(att[0]) * math.cos(att[1])
    slant_cm = int(round(100.0 * agl / max(tilt, 0.5)))          # a rangefinder measures along the body's z
    return [
        m.MAVLink_attitude_message(boot_ms, *(float(v) for v in att), 0.0, 0.0, 0.0),
        m.MAVLink_local_position_ned_message(boot_ms, *(float(v) for v in pos), *(float(v) for v in vel)),
        # Home is taken as the ground below: relative altitude reads as the height above ground.
        m.MAVLink_global_position_int_message(boot_ms, 0, 0, int(round(1000 * agl)), int(round(1000 * agl)),
                                              *(int(np.clip(round(100 * v), -32768, 32767)) for v in vel),
                                              int(math.degrees(att[2]) % 360 * 100)),
        m.MAVLink_distance_sensor_message(boot_ms, RANGE_MIN_CM, RANGE_MAX_CM,
                                          int(np.clip(slant_cm, RANGE_MIN_CM, RANGE_MAX_CM)), 0, 0, 25, 0),
    ]


def _pack(mav: Any, msg: Any) -> bytes:
    """The packet's bytes, with the sender's sequence number advanced as a real sender's is."""
    raw: bytes = msg.pack(mav)
    mav.seq = (mav.seq + 1) % 256
    return raw


def write_flight_tlog(path: Path, poses: Sequence[Pose], seed: int) -> dict:
    """Write ``path``; returns what scene.json records about it (``video_start`` for edge-run)."""
    from edge_landing.runtime.io.mavlink_conn import load_mavutil

    m = load_mavutil().mavlink
    autopilot = m.MAVLink(None, srcSystem=1, srcComponent=1)
    gcs = m.MAVLink(None, srcSystem=255, srcComponent=190)
    rng = np.random.default_rng([int(seed), 7123])
    healthy = (m.EKF_ATTITUDE | m.EKF_VELOCITY_HORIZ | m.EKF_VELOCITY_VERT | m.EKF_POS_HORIZ_REL
               | m.EKF_POS_HORIZ_ABS | m.EKF_POS_VERT_ABS | m.EKF_PRED_POS_HORIZ_REL | m.EKF_PRED_POS_HORIZ_ABS)
    end_s = poses[-1].t_s if poses else 0.0
    packets: list[tuple[float, bytes]] = []
    n = int(math.floor((end_s + PREROLL_S) * RATE_HZ + 1e-9)) + 1
    for j in range(n):
        t = -PREROLL_S + j / RATE_HZ                               # flight time: 0 at the video's first frame
        boot_ms = int(round(1000.0 * (BOOT_S + PREROLL_S + t)))
        arrival = LOG_START_UNIX_S + PREROLL_S + t + LATENCY_S + abs(float(rng.normal(0.0, JITTER_S)))
        msgs = _telemetry(m, poses, t, boot_ms)
        if j % int(RATE_HZ) == 0:   # once a second: the ground station's heartbeat (it opens the log), the autopilot's
            packets.append((LOG_START_UNIX_S + j / RATE_HZ, _pack(gcs, m.MAVLink_heartbeat_message(
                m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3))))
            msgs.insert(0, m.MAVLink_heartbeat_message(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                       m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4, m.MAV_STATE_ACTIVE, 3))
        if j % int(RATE_HZ / 2) == 0:
            msgs.append(m.MAVLink_ekf_status_report_message(healthy, 0.1, 0.1, 0.1, 0.1, 0.0))
        packets.extend((arrival + 1e-4 * k, _pack(autopilot, msg)) for k, msg in enumerate(msgs))
    packets.sort(key=lambda p: p[0])
    with open(path, "wb") as fh:
        for t_unix, raw in packets:
            fh.write(struct.pack(">Q", int(round(t_unix * 1e6))) + raw)
    return {"file": path.name, "video_start": f"+{PREROLL_S:g}", "video_start_unix_s": LOG_START_UNIX_S + PREROLL_S,
            "rate_hz": RATE_HZ, "note": "what a ground station would have logged; edge-run --tlog FILE "
                                        f"--tlog-video-start +{PREROLL_S:g}"}
