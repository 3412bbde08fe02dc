"""Which MAVLink messages are the vehicle's telemetry, and how each enters a TelemetryBuffer (ARCHITECTURE.md §12).

One rule for the live link (``mavlink_link.py``) and for a recorded telemetry log replayed beside its video
(``tlog.py``): the same messages, the same fields and units, the same trust checks in the buffer.
"""
from __future__ import annotations

from typing import Any, Tuple

from edge_landing.runtime.io.telemetry import RANGEFINDER_DOWN, TelemetryBuffer

__all__ = ["TELEMETRY_MESSAGES", "ESTIMATOR_MESSAGES", "GIMBAL_MESSAGE", "MAV_AUTOPILOT_INVALID",
           "VEHICLE_TYPES", "is_autopilot_heartbeat", "feed_telemetry", "feed_gimbal_report"]

TELEMETRY_MESSAGES = ("ATTITUDE", "GLOBAL_POSITION_INT", "DISTANCE_SENSOR", "LOCAL_POSITION_NED")
GIMBAL_MESSAGE = "GIMBAL_DEVICE_ATTITUDE_STATUS"   # read only when the telemetry has a gimbal (edge-run --gimbal)
ESTIMATOR_MESSAGES = ("EKF_STATUS_REPORT", "ESTIMATOR_STATUS")   # ArduPilot's and PX4's, read when sent
MAV_AUTOPILOT_INVALID = 8
# MAV_TYPEs of vehicles (MAVLink common.xml): generic, fixed wing, quad, coaxial, helicopter, airship, balloon,
# rocket, rover, boat, submarine, hexa, octo, tri, flapping wing, kite, the VTOLs, parafoil, dodeca, deca, generic
# multirotor, spacecraft, quadruped, gyrodyne. Anything else (an antenna tracker, which runs ArduPilot's
# AntennaTracker, says ArduPilot and streams its own ATTITUDE; a ground station, companion, gimbal, camera, ADS-B,
# radio, or a type newer than this list) is never taken for the autopilot.
VEHICLE_TYPES = frozenset({0, 1, 2, 3, 4, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 19, 20, 21, 22, 23, 24, 25,
                           28, 29, 35, 43, 45, 46, 47})


def is_autopilot_heartbeat(msg: Any) -> bool:
    """A HEARTBEAT from a vehicle's autopilot (not a ground station, antenna tracker, companion or peripheral)."""
    return msg.get_type() == "HEARTBEAT" and msg.autopilot != MAV_AUTOPILOT_INVALID and msg.type in VEHICLE_TYPES


def feed_telemetry(telemetry: TelemetryBuffer, msg: Any, arrival_s: float, mavlink: Any) -> str:
    """Hand one message from the autopilot to ``telemetry``, arrived at ``arrival_s`` (local monotonic seconds).

    Returns "telemetry" for a pose or height message, "estimator" for an estimator status, "" for anything
    else (TIMESYNC and gimbal reports have their own paths). ``mavlink``: pymavlink's dialect module."""
    kind = msg.get_type()
    if kind in ESTIMATOR_MESSAGES:
        glitch = mavlink.EKF_GPS_GLITCHING if kind == "EKF_STATUS_REPORT" else mavlink.ESTIMATOR_GPS_GLITCH
        telemetry.add_estimator_status(int(msg.flags), arrival_s, glitch)
        return "estimator"
    if kind not in TELEMETRY_MESSAGES:
        return ""
    if kind == "ATTITUDE":
        telemetry.add_attitude(msg.roll, msg.pitch, msg.yaw, msg.time_boot_ms, arrival_s,
                               body_rates_rad_s=(msg.rollspeed, msg.pitchspeed, msg.yawspeed))
    elif kind == "LOCAL_POSITION_NED":
        telemetry.add_position(msg.x, msg.y, msg.z, msg.time_boot_ms, arrival_s, velocity_ned_mps=(msg.vx, msg.vy, msg.vz))
    elif kind == "GLOBAL_POSITION_INT":
        telemetry.add_relative_alt(msg.relative_alt / 1000.0, msg.time_boot_ms, arrival_s)
    elif kind == "DISTANCE_SENSOR":
        if msg.orientation != RANGEFINDER_DOWN:
            return ""   # a proximity sensor's: not the height above ground (nor its stream)
        telemetry.add_rangefinder(msg.current_distance / 100.0, msg.time_boot_ms, arrival_s,
                                  min_m=msg.min_distance / 100.0, max_m=msg.max_distance / 100.0)
    return "telemetry"


def feed_gimbal_report(telemetry: TelemetryBuffer, msg: Any, sender: Tuple[int, int], autopilot: Tuple[int, int],
                       arrival_s: float) -> bool:
    """A GIMBAL_DEVICE_ATTITUDE_STATUS for ``telemetry``'s gimbal (edge-run --gimbal), when it comes from the
    autopilot's system: the autopilot's own report or a gimbal device's beside it (gimbal.GimbalSeries.add_report).
    True when it was kept; False when it was refused, or there is no gimbal to read or it came from elsewhere."""
    gimbal = telemetry.gimbal
    if gimbal is None or sender[0] != autopilot[0]:
        return False
    return gimbal.add_report(msg, sender, sender == autopilot, telemetry.stamp, arrival_s)
