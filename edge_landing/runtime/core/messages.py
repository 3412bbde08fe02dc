"""Typed messages passed between the stages (source -> inference -> fusion -> link).

Each message says which frame it came from, when it was captured (monotonic seconds), whether it is valid
and, if not, why, and how long each stage took.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from edge_landing.runtime.core.camera import Attitude, Mount

# Target.evidence prefixes (ARCHITECTURE.md §11).
EVIDENCE_GEOMETRY = "geometry+network"
EVIDENCE_NETWORK_ONLY = "network only"
# Appended to the evidence when the geometry baseline came from the images, not telemetry positions (§11).
EVIDENCE_IMAGE_POSE = "baseline from image pose"


@dataclass(frozen=True)
class Frame:
    """One camera image. ``rgb`` is uint8 H×W×3 in RGB order. ``valid`` is False (with a ``reason``) when the
    source could tell that the image did not decode completely (ARCHITECTURE.md §12).

    ``clock_lag_s``: how far the frame's clock ran behind ``time.monotonic()`` when the source handed it over.
    0 for a camera (stamped on the monotonic clock). A simulated or replayed flight stamps its frames with
    the flight's own time mapped onto a monotonic base fixed at its start (so frame pairing depends on the
    flight, not on how fast it rendered); a render slower than real time falls behind by this much, and the
    age rules (stale frame, target too old) count from the hand-over: ``time.monotonic() - clock_lag_s``
    is "now" on the frame's clock."""

    frame_id: int
    capture_time_s: float
    rgb: np.ndarray
    source: str = ""
    valid: bool = True
    reason: str = ""
    clock_lag_s: float = 0.0


@dataclass(frozen=True)
class Prediction:
    """Network outputs for one frame, already decoded by the model contract.

    ``depth_m``: float32 H×W planar z-depth in metres (camera frame), NaN where invalid; the model's raw
    scale times ``scale`` (1.0 when uncalibrated). ``hvo_prob``: float32 H×W×3 class probabilities
    (horizontal, vertical, other). Either may be None when the model does not have that head.
    """

    frame_id: int
    capture_time_s: float
    depth_m: Optional[np.ndarray]
    hvo_prob: Optional[np.ndarray]
    valid: bool = True
    reason: str = ""
    scale: float = 1.0
    timings_s: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Target:
    """A landing target, or the absence of one with a reason (ARCHITECTURE.md §6 step 7).

    ``position_body_frd_m``: target point in the body FRD frame at capture time (metres).
    ``position_ned_m``: absolute local NED position, when the vehicle position was known.
    Angles are from the image centre (radians, camera x right / y down); sizes are the angular
    diameter of the clear disc.
    """

    frame_id: int
    capture_time_s: float
    valid: bool
    reason: str = ""
    position_body_frd_m: Optional[np.ndarray] = None
    position_ned_m: Optional[np.ndarray] = None
    range_m: float = float("nan")
    angle_x_rad: float = float("nan")
    angle_y_rad: float = float("nan")
    size_x_rad: float = float("nan")
    size_y_rad: float = float("nan")
    clearance_m: float = float("nan")
    confidence: float = 0.0
    timings_s: dict[str, float] = field(default_factory=dict)
    # What made this spot trustworthy (ARCHITECTURE.md §11): "geometry+network" when the drone's own motion
    # confirmed it, "network only" when that was allowed without confirmation; the geometry figures of the
    # spot's cell (NaN without): baseline of the confirming frame pair, smallest obstacle height it could
    # detect, seconds since it was confirmed. ``tracked_ned_m``: on a target that is not sent, the spot the
    # network proposes and geometry has not confirmed (for overlays and logs only, never for the autopilot).
    evidence: str = ""
    geometry_baseline_m: float = float("nan")
    geometry_detectable_m: float = float("nan")
    geometry_age_s: float = float("nan")
    tracked_ned_m: Optional[np.ndarray] = None

    @property
    def geometry_confirmed(self) -> bool:
        """True when the drone's own motion confirmed this spot (only such spots may be committed, §12)."""
        return self.valid and self.evidence.startswith(EVIDENCE_GEOMETRY)

    @staticmethod
    def none(frame_id: int, capture_time_s: float, reason: str, timings_s: Optional[dict[str, float]] = None) -> Target:
        """No target for this frame, and why."""
        return Target(frame_id, capture_time_s, False, reason, timings_s=dict(timings_s or {}))


@dataclass(frozen=True)
class VehicleState:
    """Telemetry matched to a frame's capture time (ARCHITECTURE.md §3: matched to capture, not to inference end).

    ``attitude``: body FRD relative to local NED (radians). ``position_ned_m``: vehicle local NED position
    (metres) or None. ``agl_m``: height above ground (rangefinder, or relative altitude over flat terrain) or
    None; ``agl_source`` says which. ``position_epoch`` counts the times the autopilot's local frame moved
    (a position jump, e.g. an EKF reset, or a reboot): NED points of different epochs are not comparable.
    ``camera_mount``: the camera's mount at this time when a gimbal reports it (``io/gimbal.py``); None: the
    fixed mount the stages were built with (``mount_of``).
    """

    time_s: float
    attitude: Attitude = Attitude()
    position_ned_m: Optional[np.ndarray] = None
    agl_m: Optional[float] = None
    agl_source: str = ""
    position_epoch: int = 0
    camera_mount: Optional[Mount] = None

    def mount_of(self, fixed: Mount) -> Mount:
        """The camera's mount at this time: the gimbal's when reported, else ``fixed``."""
        return fixed if self.camera_mount is None else self.camera_mount


@dataclass(frozen=True)
class TelemetryMatch:
    """The vehicle state at a capture time and, when it cannot be trusted, why (``reason`` empty = fresh)."""

    state: Optional[VehicleState]
    reason: str = ""

    @property
    def fresh(self) -> bool:
        return self.state is not None and not self.reason
