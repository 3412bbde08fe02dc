"""What must hold before a target leaves, and continuity for the autopilot (ARCHITECTURE.md §12).

:class:`TelemetryWatch` says whether telemetry is fresh and announces when it is lost and found.
:class:`Continuity` keeps a committed spot (a target confirmed over several frames) and, when a frame gives
no target, re-sends that spot from memory, re-expressed in the current body frame (for ArduPilot's
BODY_FRD) or as its local NED position (PX4), as long as telemetry is fresh; the autopilot then keeps its
estimator fed while the spot is out of the camera's view (it descends vertically over it). The spot is
dropped when fresh evidence contradicts it, when telemetry goes stale, or after ``hold_s`` seconds without
confirmation, and the drop is announced. Pure numpy; the pipeline does the sending.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from edge_landing.runtime.core.messages import Target, VehicleState
from edge_landing.runtime.core.target_frames import body_from_ned, target_ned
from edge_landing.runtime.fusion.grid import GridView

log = logging.getLogger(__name__)
HELD = "held: committed spot from memory"


@dataclass(frozen=True)
class ContinuityConfig:
    """Seconds and metres."""

    commit_frames: int = 3        # a spot is committed after this many consecutive targets agree on it ...
    confirm_radius_m: float = 1.5  # ... within this distance (also what counts as confirming it later)
    hold_s: float = 20.0          # dropped after this long without a confirming target
    contradiction_radius_m: float = 1.0  # an observed, non-landable cell this close to the spot contradicts it
    held_confidence: float = 0.5  # confidence factor of a target re-sent from memory
    # Only spots the drone's own motion confirmed are committed (ARCHITECTURE.md §11): a network-only target
    # (sent under --allow-unconfirmed) is passed on but never re-sent from memory, unless this is set too.
    commit_unconfirmed: bool = False


@dataclass(frozen=True)
class CommittedSpot:
    ned_m: np.ndarray
    clearance_m: float
    confidence: float
    confirmed_s: float            # capture time of the last target that confirmed it


class Continuity:
    def __init__(self, config: ContinuityConfig = ContinuityConfig()):
        self.config = config
        self.spot: Optional[CommittedSpot] = None
        self._candidate: Optional[np.ndarray] = None
        self._candidate_frames = 0

    def drop(self) -> Optional[str]:
        """Forget the spot; returns an announcement when there was one."""
        had, self.spot, self._candidate, self._candidate_frames = self.spot, None, None, 0
        return "" if had is not None else None

    def step(self, target: Target, state: Optional[VehicleState], grid: Optional[GridView],
             reached_fusion: bool) -> Tuple[Target, str]:
        """The target to send for this frame and an announcement ('' when nothing to say).

        ``state`` is fresh telemetry at the capture time (None: not fresh, the spot is dropped);
        ``grid`` is this frame's grid (None when the frame did not reach it); ``reached_fusion`` is False for a
        frame that had no evidence at all (invalid frame or model fault): nothing is sent for it, nothing dropped.
        """
        if state is None:
            return target, self._drop_said("telemetry not fresh")
        if target.valid:
            if not (target.geometry_confirmed or self.config.commit_unconfirmed):
                return target, ""
            return target, self._observe(target, state)
        spot = self.spot
        if spot is None or not reached_fusion:
            return target, ""
        age = target.capture_time_s - spot.confirmed_s
        if age > self.config.hold_s:
            return target, self._drop_said(f"not confirmed for {age:.0f} s")
        if grid is not None and self._contradicted(grid, spot):
            return target, self._drop_said("fresh evidence contradicts it")
        body = body_from_ned(spot.ned_m, state)
        if body is None or not np.isfinite(body).all() or float(np.linalg.norm(body)) <= 0:
            return target, self._drop_said("no vehicle position to re-express it")
        rng = float(np.linalg.norm(body))
        held = Target(target.frame_id, target.capture_time_s, True, f"{HELD} ({age:.1f} s; fusion: {target.reason})",
                      position_body_frd_m=body, position_ned_m=spot.ned_m.copy(), range_m=rng,
                      size_x_rad=2.0 * math.atan2(spot.clearance_m, rng), size_y_rad=2.0 * math.atan2(spot.clearance_m, rng),
                      clearance_m=spot.clearance_m, confidence=spot.confidence * self.config.held_confidence,
                      timings_s=target.timings_s)
        return held, ""

    def _observe(self, target: Target, state: VehicleState) -> str:
        ned = target_ned(target, state)
        if ned is None:
            return ""
        r = self.config.confirm_radius_m
        if self.spot is not None and float(np.linalg.norm(ned[:2] - self.spot.ned_m[:2])) <= r:
            self.spot = CommittedSpot(ned, target.clearance_m, target.confidence, target.capture_time_s)
            return ""
        if self._candidate is not None and float(np.linalg.norm(ned[:2] - self._candidate[:2])) <= r:
            self._candidate_frames += 1
        else:
            self._candidate, self._candidate_frames = ned, 1
        if self._candidate_frames >= self.config.commit_frames:
            moved = self.spot is not None
            self.spot = CommittedSpot(ned, target.clearance_m, target.confidence, target.capture_time_s)
            self._candidate, self._candidate_frames = None, 0
            return "spot moved" if moved else ""
        return ""

    def _contradicted(self, grid: GridView, spot: CommittedSpot) -> bool:
        """An observed cell near the spot that this grid judges not landable."""
        if grid.frame != "ned":
            return False
        seen = grid.observed
        n, e = float(spot.ned_m[0]), float(spot.ned_m[1])
        k = int(math.ceil(self.config.contradiction_radius_m / grid.cell_m))
        centre = grid.cell_of(n, e)
        if centre is None:
            return False
        rows, cols = grid.shape
        r0, r1 = max(centre[0] - k, 0), min(centre[0] + k + 1, rows)
        c0, c1 = max(centre[1] - k, 0), min(centre[1] + k + 1, cols)
        bad = seen[r0:r1, c0:c1] & ~grid.landable[r0:r1, c0:c1]
        if not bad.any():
            return False
        centres = grid.cell_centres_m()[r0:r1, c0:c1]
        dist = np.hypot(centres[..., 0] - n, centres[..., 1] - e)
        return bool((bad & (dist <= self.config.contradiction_radius_m)).any())

    def _drop_said(self, why: str) -> str:
        if self.spot is None:
            self._candidate, self._candidate_frames = None, 0
            return ""
        self.drop()
        log.warning("committed landing spot dropped: %s", why)
        return f"spot dropped: {why}"
