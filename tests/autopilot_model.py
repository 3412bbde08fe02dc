"""A small multicopter autopilot MODEL for the closed-loop tests. TEST DOUBLE, not a product feature.

No real autopilot can be installed in CI, so this stands in for ArduCopter in the closed loop (the house rule:
a test double only where the real thing cannot be installed). It speaks real MAVLink 2 over loopback UDP with
pymavlink, to one or more peers (``udpout:`` each, like MAVProxy's ``--out``): the closed-loop driver, edge-run's
link and the sim-follow camera each get the full telemetry stream and may send commands.

What it models, from ArduPilot's documented precision-landing behaviour (docs/closed_loop.md lists it):
- HEARTBEAT 1 Hz (MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA, ArduCopter mode numbers); ATTITUDE,
  GLOBAL_POSITION_INT (relative_alt), LOCAL_POSITION_NED, DISTANCE_SENSOR (orientation 25, cm) at 20 Hz with
  ``time_boot_ms``; EKF_STATUS_REPORT (a healthy EKF with GPS) with them; COMMAND_ACK for every COMMAND_LONG;
  TIMESYNC answered (``tc1`` = its boot clock in ns, ``ts1`` echoed, as GCS_Common.cpp does); PARAM_REQUEST_READ
  answered for its precision-landing parameters (set up for a MAVLink companion), as GCS_Param.cpp does;
  STATUSTEXT on estimator events.
- LANDING_TARGET: frame BODY_FRD (12) or LOCAL_FRD only ("Plnd: Frame not supported" otherwise),
  ``position_valid = 1`` and ``distance > 0``; only the direction (x, y, z)/|.| is used, rotated by the attitude
  of ``plnd_lag_s`` ago; the range comes from its own height above ground (PLND_EST_TYPE 0, raw sensor).
- A message is a new measurement only when its ``time_usec``, in milliseconds, differs from the last one used
  (AC_PrecLand::retrieve_los_meas compares the jitter-corrected millisecond); a repeat counts as a duplicate
  and feeds nothing.
- The estimator needs updates < 0.5 s apart for 2 s ("PrecLand: Init Complete") and drops the target after
  2 s without one ("PrecLand: Target Lost"; it then needs a new init).
- LAND with a target: fly horizontally to it at altitude, descend only within ``xy_dist_max_m`` (PLND_XY_DIST_MAX,
  2.5 m) of it, then vertically over it; LAND without a target: descend where it is. Touchdown when the height
  above the world's surface (ray cast straight down) reaches zero; then it disarms, as ArduCopter does.
- Kinematics: velocity and acceleration limits, a small tilt in the direction of acceleration.
  Simplified against ArduCopter: descent 2.5 m/s above 10 m and 1.0 m/s below (ArduCopter: LAND_SPEED 0.5 m/s).

Run: ``python -m tests.autopilot_model --style urban --seed 3 --out udpout:127.0.0.1:14560 ...``.
"""
from __future__ import annotations

import argparse
import math
import time
from collections import deque
from dataclasses import dataclass
from typing import Deque, List, Optional, Tuple

import numpy as np

from edge_landing.benchmarks.autopilot_params import PRECLAND_PARAMS, send_param
from edge_landing.runtime.core.camera import Attitude
from edge_landing.runtime.io.mavlink_link import load_mavutil
from edge_landing.sim import build_world
from edge_landing.sim.follow import height_above_ground_m, place_home

GUIDED, LAND, STABILIZE = 4, 9, 0
FRAME_BODY_FRD, FRAME_LOCAL_FRD = 12, 20
ORIGIN_LAT_LON_ALT = (-35.363261, 149.165230, 584.0)   # ArduPilot SITL's default home (CMAC)
G = 9.81


@dataclass(frozen=True)
class ModelConfig:
    style: str = "suburban"
    seed: int = 0
    outs: Tuple[str, ...] = ("udpout:127.0.0.1:14560",)
    physics_hz: float = 50.0
    telemetry_hz: float = 20.0
    plnd_lag_s: float = 0.1
    xy_dist_max_m: float = 2.5
    init_gap_s: float = 0.5
    init_time_s: float = 2.0
    lost_after_s: float = 2.0
    speed_h_ms: float = 5.0
    climb_ms: float = 3.0
    descent_high_ms: float = 2.5
    descent_low_ms: float = 1.0
    land_alt_low_m: float = 10.0
    accel_ms2: float = 3.0
    yaw_rate_rad_s: float = 1.0
    max_tilt_rad: float = math.radians(20)
    # A stabilised gimbal holding the camera at this pitch below the horizon, yaw with the heading, reported as
    # ArduPilot reports the gimbals it drives (GIMBAL_DEVICE_ATTITUDE_STATUS from the autopilot, its clock).
    gimbal_pitch_deg: Optional[float] = None


class PrecLand:
    """The precision-landing estimator: target position in the autopilot's local NED, and its life cycle."""

    def __init__(self, cfg: ModelConfig):
        self.cfg = cfg
        self.target_ned: Optional[np.ndarray] = None
        self.last_update_s = -math.inf
        self.streak_start_s = -math.inf
        self.initialised = False
        self.used = 0

    def acquired(self, now_s: float) -> bool:
        return self.initialised and now_s - self.last_update_s < self.cfg.lost_after_s

    def update(self, now_s: float, target_ned: np.ndarray) -> Optional[str]:
        """A measurement arrived; returns a STATUSTEXT to announce, if any."""
        if now_s - self.last_update_s >= self.cfg.init_gap_s:
            self.streak_start_s = now_s
        self.last_update_s = now_s
        self.target_ned = target_ned
        self.used += 1
        if not self.initialised and now_s - self.streak_start_s >= self.cfg.init_time_s:
            self.initialised = True
            return "PrecLand: Init Complete"
        return None

    def expire(self, now_s: float) -> Optional[str]:
        if self.initialised and now_s - self.last_update_s >= self.cfg.lost_after_s:
            self.initialised = False
            return "PrecLand: Target Lost"
        return None


class AutopilotModel:
    """The vehicle (world NED, the world's own frame) and its MAVLink side; ``run`` blocks until disarmed
    after a landing, or ``duration_s``."""

    def __init__(self, cfg: ModelConfig):
        self.cfg = cfg
        self.world = build_world(cfg.style, cfg.seed)
        self.home = place_home(self.world)                     # world NED of the local NED origin
        self.pos = self.home.copy()
        self.vel = np.zeros(3)
        self.acc = np.zeros(3)
        self.yaw = 0.0
        self.attitude = Attitude()
        self.armed, self.mode, self.landed_once = False, STABILIZE, False
        self.target_local: Optional[np.ndarray] = None           # GUIDED position target (local NED)
        self.target_yaw: Optional[float] = None
        self.hold_xy: Optional[np.ndarray] = None                # LAND without a target: where it stopped
        self.precland = PrecLand(cfg)
        self.history: Deque[Tuple[float, Attitude, np.ndarray]] = deque(maxlen=int(cfg.physics_hz * 2))
        self.rejected = 0
        self.duplicates = 0                                    # LANDING_TARGETs repeating the last one's time_usec ms
        self.last_stamp_ms: Optional[int] = None
        self.boot_s = time.monotonic()
        self.mavutil = load_mavutil()
        self.conns = [self.mavutil.mavlink_connection(u, source_system=1, source_component=1) for u in cfg.outs]

    # -- MAVLink out ----------------------------------------------------------------------------------
    def _send_all(self, msg) -> None:
        for c in self.conns:
            try:
                c.mav.send(msg)
            except OSError:
                pass  # a peer not listening yet

    def _time_boot_ms(self) -> int:
        return int((time.monotonic() - self.boot_s) * 1000)

    def status(self, text: str, severity: int = 6) -> None:
        self._send_all(self.mavutil.mavlink.MAVLink_statustext_message(severity, text.encode()[:50]))

    def heartbeat(self) -> None:
        m = self.mavutil.mavlink
        base = m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (m.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
        state = m.MAV_STATE_ACTIVE if self.armed else m.MAV_STATE_STANDBY
        self._send_all(m.MAVLink_heartbeat_message(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, base,
                                                   self.mode, state, 3))

    def _body_rates(self, t_ms: int, a: Attitude) -> tuple[float, float, float]:
        """Gyro rates (body p, q, r, rad/s) as ArduPilot fills ATTITUDE's rollspeed..yawspeed: here from the change of
        the model's attitude since the last report (Euler rates turned into body rates)."""
        last, self._last_attitude = getattr(self, "_last_attitude", None), (t_ms, a)
        if last is None or t_ms <= last[0]:
            return 0.0, 0.0, 0.0
        dt = (t_ms - last[0]) / 1000.0
        d_roll, d_pitch = (a.roll_rad - last[1].roll_rad) / dt, (a.pitch_rad - last[1].pitch_rad) / dt
        d_yaw = math.remainder(a.yaw_rad - last[1].yaw_rad, 2.0 * math.pi) / dt
        sr, cr, sp, cp = math.sin(a.roll_rad), math.cos(a.roll_rad), math.sin(a.pitch_rad), math.cos(a.pitch_rad)
        return d_roll - d_yaw * sp, d_pitch * cr + d_yaw * sr * cp, -d_pitch * sr + d_yaw * cr * cp

    def telemetry(self) -> None:
        m = self.mavutil.mavlink
        t = self._time_boot_ms()
        local = self.pos - self.home
        a = self.attitude
        agl = self.agl_m()
        lat0, lon0, alt0 = ORIGIN_LAT_LON_ALT
        lat = lat0 + math.degrees(local[0] / 6378137.0)
        lon = lon0 + math.degrees(local[1] / (6378137.0 * math.cos(math.radians(lat0))))
        self._send_all(m.MAVLink_attitude_message(t, a.roll_rad, a.pitch_rad, a.yaw_rad, *self._body_rates(t, a)))
        self._send_all(m.MAVLink_local_position_ned_message(t, *(float(v) for v in local), *(float(v) for v in self.vel)))
        self._send_all(m.MAVLink_global_position_int_message(
            t, int(lat * 1e7), int(lon * 1e7), int((alt0 - local[2]) * 1000), int(-local[2] * 1000),
            *(int(v * 100) for v in self.vel), int(math.degrees(self.yaw) % 360 * 100)))
        self._send_all(m.MAVLink_distance_sensor_message(t, 20, 10000, int(round(max(agl, 0.0) * 100)),
                                                         m.MAV_DISTANCE_SENSOR_LASER, 0, 25, 0))
        # A healthy EKF3 with GPS (ArduPilot streams EKF_STATUS_REPORT with its extended status): edge-run believes it.
        healthy = (m.EKF_ATTITUDE | m.EKF_VELOCITY_HORIZ | m.EKF_VELOCITY_VERT | m.EKF_POS_HORIZ_REL
                   | m.EKF_POS_HORIZ_ABS | m.EKF_POS_VERT_ABS | m.EKF_PRED_POS_HORIZ_REL | m.EKF_PRED_POS_HORIZ_ABS)
        self._send_all(m.MAVLink_ekf_status_report_message(healthy, 0.05, 0.05, 0.05, 0.05, 0.0))
        if self.cfg.gimbal_pitch_deg is not None:
            half = math.radians(self.cfg.gimbal_pitch_deg) / 2.0    # (w, x, y, z) of a pitch alone
            flags = (m.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME | m.GIMBAL_DEVICE_FLAGS_ROLL_LOCK
                     | m.GIMBAL_DEVICE_FLAGS_PITCH_LOCK)
            self._send_all(m.MAVLink_gimbal_device_attitude_status_message(
                0, 0, t, flags, [math.cos(half), 0.0, math.sin(half), 0.0], math.nan, math.nan, math.nan, 0,
                math.nan, math.nan, 0))

    # -- MAVLink in -----------------------------------------------------------------------------------
    def receive(self, now_s: float) -> None:
        for c in self.conns:
            for _ in range(50):
                try:
                    msg = c.recv_msg()
                except OSError:
                    break
                if msg is None:
                    break
                self._handle(c, msg, now_s)

    def _handle(self, conn, msg, now_s: float) -> None:
        m = self.mavutil.mavlink
        kind = msg.get_type()
        if kind == "COMMAND_LONG":
            ok = self._command(msg)
            conn.mav.command_ack_send(msg.command, m.MAV_RESULT_ACCEPTED if ok else m.MAV_RESULT_DENIED)
        elif kind == "SET_MODE":
            self._set_mode(int(msg.custom_mode))
        elif kind == "SET_POSITION_TARGET_LOCAL_NED" and msg.coordinate_frame == m.MAV_FRAME_LOCAL_NED:
            self.target_local = np.array([msg.x, msg.y, msg.z])
            yaw_ignored = msg.type_mask & m.POSITION_TARGET_TYPEMASK_YAW_IGNORE
            self.target_yaw = None if yaw_ignored else float(msg.yaw)
        elif kind == "LANDING_TARGET":
            self._landing_target(msg, now_s)
        elif kind == "TIMESYNC" and msg.tc1 == 0:   # ArduPilot answers with its boot clock at receipt, in ns
            conn.mav.timesync_send(int((time.monotonic() - self.boot_s) * 1e9), msg.ts1)
        elif kind == "PARAM_REQUEST_READ":
            self._param(conn, str(msg.param_id).rstrip("\x00"))

    def _param(self, conn, name: str) -> None:
        """Its precision-landing parameters, as ArduPilot answers (benchmarks.autopilot_params)."""
        params = {**PRECLAND_PARAMS, "PLND_LAG": self.cfg.plnd_lag_s, "PLND_XY_DIST_MAX": self.cfg.xy_dist_max_m}
        if name in params:
            send_param(conn.mav, name, params)

    def _command(self, msg) -> bool:
        m = self.mavutil.mavlink
        if msg.command == m.MAV_CMD_COMPONENT_ARM_DISARM:
            if msg.param1 == 1 and self.mode == GUIDED and self.agl_m() < 0.5:
                self.armed = True
            elif msg.param1 == 0 and self.agl_m() < 0.5:
                self.armed = False
            return self.armed == (msg.param1 == 1)
        if msg.command == m.MAV_CMD_NAV_TAKEOFF:
            if not (self.armed and self.mode == GUIDED):
                return False
            self.target_local = np.array([*(self.pos - self.home)[:2], -float(msg.param7)])
            return True
        if msg.command == m.MAV_CMD_DO_SET_MODE:
            return self._set_mode(int(msg.param2))
        if msg.command == m.MAV_CMD_NAV_LAND:
            return self._set_mode(LAND)
        return msg.command == m.MAV_CMD_SET_MESSAGE_INTERVAL  # streams run at 20 Hz whatever is asked

    def _set_mode(self, mode: int) -> bool:
        if mode not in (GUIDED, LAND, STABILIZE):
            return False
        if mode == LAND and self.mode != LAND:
            self.hold_xy = None
        self.mode = mode
        return True

    def _landing_target(self, msg, now_s: float) -> None:
        if msg.frame not in (FRAME_BODY_FRD, FRAME_LOCAL_FRD):
            self.status("Plnd: Frame not supported", 4)
            self.rejected += 1
            return
        xyz = np.array([msg.x, msg.y, msg.z], np.float64)
        if getattr(msg, "position_valid", 0) != 1 or not msg.distance > 0 or not np.linalg.norm(xyz) > 0:
            self.rejected += 1
            return
        stamp_ms = int(msg.time_usec) // 1000
        if stamp_ms == self.last_stamp_ms:
            self.duplicates += 1
            return
        self.last_stamp_ms = stamp_ms
        lagged_att, lagged_pos = self._lagged(now_s - self.cfg.plnd_lag_s)
        direction = lagged_att.ned_from_body() @ (xyz / np.linalg.norm(xyz))
        agl = self.agl_m()
        if direction[2] <= 0.05 or agl <= 0:
            self.rejected += 1
            return
        target = (lagged_pos - self.home) + direction * (agl / direction[2])   # local NED of the target
        note = self.precland.update(now_s, target)
        if note:
            self.status(note)

    def _lagged(self, t_s: float) -> Tuple[Attitude, np.ndarray]:
        for t, att, pos in reversed(self.history):
            if t <= t_s:
                return att, pos
        return self.attitude, self.pos.copy()

    # -- physics --------------------------------------------------------------------------------------
    def agl_m(self) -> float:
        return height_above_ground_m(self.world, self.pos)

    def _desired_velocity(self, now_s: float) -> np.ndarray:
        c = self.cfg
        local = self.pos - self.home
        if self.mode == GUIDED and self.target_local is not None:
            v = _approach(self.target_local[:2] - local[:2], c.speed_h_ms, c.accel_ms2)
            dz = self.target_local[2] - local[2]
            vz = float(np.clip(dz, -c.climb_ms, c.descent_high_ms))
            return np.array([v[0], v[1], vz])
        if self.mode == LAND:
            agl = self.agl_m()
            descent = c.descent_high_ms if agl > c.land_alt_low_m else c.descent_low_ms
            if self.precland.acquired(now_s) and self.precland.target_ned is not None:
                self.hold_xy = None
                offset = self.precland.target_ned[:2] - local[:2]
                v = _approach(offset, c.speed_h_ms, c.accel_ms2)
                vz = descent if np.linalg.norm(offset) <= c.xy_dist_max_m else 0.0
                return np.array([v[0], v[1], vz])
            if self.hold_xy is None:
                self.hold_xy = local[:2] + self.vel[:2] * np.linalg.norm(self.vel[:2]) / (2 * c.accel_ms2)
            v = _approach(self.hold_xy - local[:2], c.speed_h_ms, c.accel_ms2)
            return np.array([v[0], v[1], descent])
        return np.zeros(3)

    def step(self, now_s: float, dt: float) -> None:
        note = self.precland.expire(now_s)
        if note:
            self.status(note)
        if not self.armed:
            self.vel[:] = 0.0
            self.acc[:] = 0.0
        else:
            want = self._desired_velocity(now_s)
            dv = want - self.vel
            max_dv = self.cfg.accel_ms2 * dt
            n = np.linalg.norm(dv)
            self.acc = (dv if n <= max_dv else dv * max_dv / n) / dt
            self.vel = self.vel + self.acc * dt
            self.pos = self.pos + self.vel * dt
            if self.target_yaw is not None and self.mode == GUIDED:
                err = (self.target_yaw - self.yaw + math.pi) % (2 * math.pi) - math.pi
                self.yaw += float(np.clip(err, -self.cfg.yaw_rate_rad_s * dt, self.cfg.yaw_rate_rad_s * dt))
            if self.vel[2] > 0 and self.agl_m() <= 0.02:
                self._touchdown()
        self.attitude = self._tilt()
        self.history.append((now_s, self.attitude, self.pos.copy()))

    def _touchdown(self) -> None:
        self.pos[2] -= self.agl_m()
        self.vel[:] = 0.0
        self.acc[:] = 0.0
        self.armed, self.landed_once = False, True
        self.status("Disarming motors")

    def _tilt(self) -> Attitude:
        """Lean into the horizontal acceleration (plus a little drag): pitch nose down to speed up forward."""
        a_h = self.acc[:2] + 0.05 * self.vel[:2]
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        fwd, right = c * a_h[0] + s * a_h[1], -s * a_h[0] + c * a_h[1]
        lim = self.cfg.max_tilt_rad
        return Attitude(float(np.clip(math.atan2(right, G), -lim, lim)),
                        float(np.clip(-math.atan2(fwd, G), -lim, lim)), float(self.yaw))

    def run(self, duration_s: float = 0.0) -> None:
        dt = 1.0 / self.cfg.physics_hz
        start = last = time.monotonic()
        next_tel = next_hb = start
        while not (self.landed_once and not self.armed and time.monotonic() - last > 3.0):
            now = time.monotonic()
            self.receive(now)
            self.step(now, dt)
            if now >= next_tel:
                self.telemetry()
                next_tel += 1.0 / self.cfg.telemetry_hz
            if now >= next_hb:
                self.heartbeat()
                next_hb += 1.0
            if self.armed or not self.landed_once:
                last = now
            if duration_s and now - start > duration_s:
                break
            time.sleep(max(0.0, start + dt * math.ceil((time.monotonic() - start) / dt + 1e-9) - time.monotonic()))


def _approach(offset: np.ndarray, speed_max: float, accel: float) -> np.ndarray:
    """Velocity towards ``offset`` that can still stop in time (a square-root controller, as ArduPilot's)."""
    dist = float(np.linalg.norm(offset))
    if dist < 1e-6:
        return np.zeros(2)
    speed = min(speed_max, math.sqrt(2 * accel * dist * 0.8), 1.5 * dist)
    return offset / dist * speed


def main(argv: Optional[List[str]] = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--style", default="suburban")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", action="append", required=True, help="udpout:HOST:PORT of a peer (repeat)")
    p.add_argument("--plnd-lag", type=float, default=0.1)
    p.add_argument("--duration", type=float, default=0.0, help="stop after S seconds (0: after the landing)")
    p.add_argument("--gimbal-pitch", type=float, default=None, help="report a stabilised gimbal at this pitch "
                   "(degrees, negative = below the horizon)")
    a = p.parse_args(argv)
    AutopilotModel(ModelConfig(a.style, a.seed, tuple(a.out), plnd_lag_s=a.plnd_lag,
                               gimbal_pitch_deg=a.gimbal_pitch)).run(a.duration)


if __name__ == "__main__":
    main()
