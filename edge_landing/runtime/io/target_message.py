"""What a LANDING_TARGET carries (ARCHITECTURE.md §8, §12): its frame and vector, its time stamp, its fields.

The link (``mavlink_link.py``) decides whether a target may leave now; this module says what the message holds.
ArduPilot consumes a body-frame vector (MAV_FRAME_BODY_FRD) and takes only its direction, with the metric range
from its own height; PX4 consumes the target's absolute local NED position. Pure, no I/O.
"""
from __future__ import annotations

import math
from typing import Any, Optional, Tuple

import numpy as np

from edge_landing.runtime.core.messages import Target, VehicleState
from edge_landing.runtime.core.target_frames import target_ned
from edge_landing.runtime.io.link_config import Autopilot

__all__ = ["FRAME_LOCAL_NED", "FRAME_BODY_FRD", "TARGET_TYPE_VISION_OTHER", "TargetStamps", "body_vector",
           "message_vector", "landing_target_message"]
FRAME_LOCAL_NED, FRAME_BODY_FRD = 1, 12
TARGET_TYPE_VISION_OTHER = 3


def body_vector(target: Target) -> Tuple[Optional[np.ndarray], str]:
    """The target's body-frame vector (FRD, m), or (None, why not) for no target or a vector that is not finite
    or of zero length (ArduPilot needs a distance > 0)."""
    if not target.valid or target.position_body_frd_m is None:
        return None, target.reason or "no target"
    body = np.asarray(target.position_body_frd_m, dtype=np.float64)
    if not np.isfinite(body).all() or float(np.linalg.norm(body)) <= 0:
        return None, "target position is not finite"
    return body, ""


def message_vector(target: Target, body_frd_m: np.ndarray, state: Optional[VehicleState],
                   autopilot: Autopilot) -> Tuple[Optional[np.ndarray], int]:
    """(x, y, z as a 3-vector, MAV_FRAME) for the autopilot: the body vector for ArduPilot (BODY_FRD), the absolute
    local NED position for PX4 (LOCAL_NED; the vector is None when no telemetry position places the target: PX4
    has no use for a body vector)."""
    if autopilot is Autopilot.PX4:
        return target_ned(target, state), FRAME_LOCAL_NED
    return body_frd_m, FRAME_BODY_FRD


class TargetStamps:
    """``time_usec`` values, each in a later millisecond than the last one sent: ArduPilot takes a message as a new
    measurement only when its (jitter-corrected) millisecond changes (AC_PrecLand::retrieve_los_meas), so a re-send
    that kept its stamp would be dropped as a duplicate and would not keep its estimator fed."""

    def __init__(self) -> None:
        self._last_ms: Optional[int] = None

    def next_us(self, stamp_s: float) -> int:
        """The stamp for a pose time, moved to the millisecond after the last sent one when not later. Stamps are
        pose times, which only grow, or capture times, a little older; so the push is a millisecond or a few."""
        stamp_us = int(stamp_s * 1e6)
        if self._last_ms is not None and stamp_us // 1000 <= self._last_ms:
            stamp_us = (self._last_ms + 1) * 1000 + stamp_us % 1000
        return stamp_us

    def sent(self, stamp_us: int) -> None:
        """Record a stamp that left the socket."""
        self._last_ms = stamp_us // 1000


def landing_target_message(mavlink: Any, target: Target, xyz: np.ndarray, frame: int, stamp_us: int) -> Any:
    """The LANDING_TARGET (pymavlink's ``mavlink`` dialect module) with the target's own angles and sizes
    (core.target_frames sets them with its body vector), x, y, z as given (``message_vector``), distance the body
    vector's length, ``position_valid`` 1, type VISION_OTHER; non-finite angles or sizes go as 0."""
    distance = float(np.linalg.norm(np.asarray(target.position_body_frd_m, dtype=np.float64)))
    return mavlink.MAVLink_landing_target_message(
        stamp_us, 0, frame, _finite(target.angle_x_rad), _finite(target.angle_y_rad), distance,
        _finite(target.size_x_rad), _finite(target.size_y_rad), float(xyz[0]), float(xyz[1]), float(xyz[2]),
        [1.0, 0.0, 0.0, 0.0], TARGET_TYPE_VISION_OTHER, 1)


def _finite(value: float) -> float:
    return float(value) if math.isfinite(value) else 0.0
