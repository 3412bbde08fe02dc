"""The camera's orientation reported live by a gimbal (MAVLink GIMBAL_DEVICE_ATTITUDE_STATUS), matched to a
frame's capture time (ARCHITECTURE.md §3: "a gimbal may report the mount live").

Frames. The message's quaternion (w, x, y, z) rotates the gimbal's FRD axes (x: the optical axis) into a
reference frame whose roll and pitch are the horizon's (a stabilised camera keeps them while the vehicle tilts)
and whose yaw is north's (earth frame) or the vehicle's heading (vehicle frame), as the flags say:
YAW_IN_EARTH_FRAME or YAW_IN_VEHICLE_FRAME, and for older devices that set neither, YAW_LOCK means the earth
frame (MAVLink's gimbal protocol v2). With the vehicle's attitude at the same time, the camera's mount for that
frame (body <- camera) is ``R_ned<-body^T · Rz(heading) · R(q)``, heading = the vehicle's yaw in the vehicle
frame and 0 in the earth frame.

Trust (ARCHITECTURE.md §12): a sample is refused when its quaternion is not finite or not of unit length, when
the device reports a failure or is retracted, or when it is no newer than the last; a frame gets no mount when no
sample lies within ``window_s`` of its capture time or the newest arrived more than ``fresh_s`` ago. A frame
without a mount gets no telemetry match, so nothing is placed or sent from an orientation nobody reported.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any, Callable, Dict, Optional, Tuple

import numpy as np

from edge_landing.runtime.core.camera import Attitude, Mount, rot_z
from edge_landing.runtime.core.choices import ChoiceEnum
from edge_landing.runtime.io.series import TimeSeries

__all__ = ["GimbalConfig", "GimbalSeries", "GimbalSource", "mount_from_gimbal", "rotation_from_quaternion",
           "FLAG_RETRACT", "FLAG_YAW_LOCK", "FLAG_YAW_IN_VEHICLE_FRAME", "FLAG_YAW_IN_EARTH_FRAME"]
log = logging.getLogger(__name__)
# GIMBAL_DEVICE_FLAGS (MAVLink common.xml)
FLAG_RETRACT, FLAG_YAW_LOCK, FLAG_YAW_IN_VEHICLE_FRAME, FLAG_YAW_IN_EARTH_FRAME = 1, 16, 32, 64


class GimbalSource(ChoiceEnum):
    """Where the camera's orientation comes from: the fixed mount (``--mount-pitch``) or the gimbal's reports."""

    NONE = "none"
    MAVLINK = "mavlink"

    @classmethod
    def _label(cls) -> str:
        return "gimbal source"


@dataclass(frozen=True)
class GimbalConfig:
    """Matching and freshness (seconds). Gimbals report at a low rate (the protocol suggests 5 Hz)."""

    window_s: float = 0.25       # a frame takes the samples around it when they are at most 2 × this apart
    fresh_s: float = 0.6         # the newest sample must have arrived at most this long ago
    history_s: float = 5.0
    max_samples: int = 1024
    unit_tolerance: float = 0.05  # |q| may differ from 1 by this much (float32 on the wire), else refused


def rotation_from_quaternion(w: float, x: float, y: float, z: float) -> np.ndarray:
    """3×3 rotation of a unit quaternion (Hamilton, w first, as MAVLink sends it): v_ref = R @ v_gimbal."""
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ], dtype=np.float64)


def mount_from_gimbal(q_wxyz: np.ndarray, earth_frame: bool, attitude: Attitude) -> Mount:
    """The mount (body <- camera) of a camera whose gimbal reports ``q_wxyz`` (yaw from north when
    ``earth_frame``, else from the heading) while the vehicle holds ``attitude``."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    ref = np.eye(3) if earth_frame else rot_z(attitude.yaw_rad)
    ned_from_gimbal = ref @ rotation_from_quaternion(*(q / np.linalg.norm(q)))
    return Mount.from_body_from_gimbal(attitude.ned_from_body().T @ ned_from_gimbal)


def yaw_in_earth_frame(flags: int) -> bool:
    """Which frame the quaternion's yaw is in (protocol v2; YAW_LOCK decides for devices that set neither)."""
    if flags & FLAG_YAW_IN_EARTH_FRAME:
        return True
    if flags & FLAG_YAW_IN_VEHICLE_FRAME:
        return False
    return bool(flags & FLAG_YAW_LOCK)


class GimbalSeries:
    """Thread-safe time series of the gimbal's quaternion (the link thread adds, the pipeline asks ``mount_at``)."""

    def __init__(self, config: GimbalConfig = GimbalConfig()):
        self.config = config
        self._lock = threading.Lock()
        self._series = TimeSeries(config.history_s, config.max_samples)
        self._earth: Optional[bool] = None          # the frame of the samples kept
        self.device: Optional[Tuple[int, int]] = None   # (component, gimbal_device_id) of the one gimbal read
        self._rejected: Counter[str] = Counter()
        self.samples = 0

    def rejected(self) -> Dict[str, int]:
        with self._lock:
            return dict(self._rejected)

    def add(self, q_wxyz: Tuple[float, float, float, float], flags: int, failure_flags: int,
            sample_s: Optional[float], arrival_s: Optional[float] = None, device: Tuple[int, int] = (0, 0)) -> bool:
        """One report, ``sample_s`` on the local monotonic clock (None: its time stamp could not be mapped). Only
        the first ``device`` heard is read: a second camera's reports would be mixed in. Never raises; False (and
        counted) when refused."""
        arrival = time.monotonic() if arrival_s is None else arrival_s
        with self._lock:
            if self.device is None:
                self.device = device
                log.info("gimbal found: component %d, device %d; other gimbals' reports are ignored", *device)
            why = "another gimbal's report" if device != self.device else self._refuse(
                q_wxyz, flags, failure_flags, sample_s)
            if why or sample_s is None:
                self._rejected[why] += 1
                return False
            q = np.asarray(q_wxyz, dtype=np.float64)
            q = q / np.linalg.norm(q)
            earth = yaw_in_earth_frame(flags)
            if earth != self._earth:        # the reference frame changed: the samples kept mean something else
                self._series.clear()
                self._earth = earth
            elif self._series.values and float(np.dot(self._series.values[-1], q)) < 0:
                q = -q                      # the same rotation on the near hemisphere, so interpolation is short
            if not self._series.add(sample_s, q, arrival):
                self._rejected["gimbal report not newer than the last one"] += 1
                return False
            self.samples += 1
            return True

    def add_report(self, msg: Any, sender: Tuple[int, int], from_autopilot: bool,
                   stamp: Callable[[float, float], Optional[float]], arrival_s: Optional[float] = None) -> bool:
        """A GIMBAL_DEVICE_ATTITUDE_STATUS from the autopilot's system, arrived at ``arrival_s`` (default now). The
        autopilot's own reports (it reports the gimbals it drives) are on its clock: ``stamp`` maps them as
        telemetry. A gimbal device's are on the device's clock, unknown here: timed on arrival."""
        arrival = time.monotonic() if arrival_s is None else arrival_s
        sample_s = stamp(msg.time_boot_ms, arrival) if from_autopilot else arrival
        device = (sender[1], int(getattr(msg, "gimbal_device_id", 0) or 0))
        return self.add(tuple(msg.q), int(msg.flags), int(msg.failure_flags), sample_s, arrival, device)

    def _refuse(self, q_wxyz: Tuple[float, float, float, float], flags: int, failure_flags: int,
                sample_s: Optional[float]) -> str:
        if sample_s is None or not math.isfinite(sample_s):
            return "gimbal report without a usable time stamp"
        values = [float(v) for v in q_wxyz]
        if len(values) != 4 or not all(math.isfinite(v) for v in values):
            return "gimbal quaternion not finite"
        if abs(math.sqrt(sum(v * v for v in values)) - 1.0) > self.config.unit_tolerance:
            return "gimbal quaternion not of unit length"
        if failure_flags:
            return "gimbal reports a failure"
        if flags & FLAG_RETRACT:
            return "gimbal retracted"
        if flags & FLAG_YAW_IN_EARTH_FRAME and flags & FLAG_YAW_IN_VEHICLE_FRAME:
            return "gimbal flags name both yaw frames"
        return ""

    def mount_at(self, capture_time_s: float, attitude: Attitude,
                 now_s: Optional[float] = None) -> Tuple[Optional[Mount], str]:
        """The camera's mount at a capture time, or (None, why not); freshness is judged only with ``now_s``."""
        with self._lock:
            q, earth = self._series.at(capture_time_s, self.config.window_s), bool(self._earth)
        why = "" if q is not None and now_s is None else self.why_not(capture_time_s, now_s)
        if why or q is None:    # (q None with no reason: a report arrived between the two reads)
            return None, why or f"no gimbal attitude within {self.config.window_s:g} s of the capture time"
        return mount_from_gimbal(q, earth, attitude), ""

    def why_not(self, capture_time_s: float, now_s: Optional[float] = None) -> str:
        """'' when a report covers the capture time (and, with ``now_s``, the newest is fresh), else why not; no
        rotation is computed (``TelemetryBuffer.lookup`` asks this of the state ``state_at`` already built)."""
        c = self.config
        with self._lock:
            last = self._series.last_arrival_s
            covered = self._series.at(capture_time_s, c.window_s) is not None
            rejected = dict(self._rejected) if last == -math.inf else {}
        if last == -math.inf:
            detail = f" ({sum(rejected.values())} rejected: {max(rejected, key=rejected.__getitem__)})" if rejected else ""
            return "no gimbal attitude" + detail
        if now_s is not None and now_s - last > c.fresh_s:
            return f"gimbal attitude stale: last report {now_s - last:.2f} s ago"
        return "" if covered else f"no gimbal attitude within {c.window_s:g} s of the capture time"
