"""What must hold before a target leaves, and continuity for the autopilot (ARCHITECTURE.md §12).

:class:`TelemetryWatch` says whether telemetry is fresh and announces when it is lost and found.
:class:`Continuity` keeps a committed spot (a target confirmed over several frames) and, when a frame gives
no target, re-sends that spot from memory, re-expressed in the current body frame (for ArduPilot's
BODY_FRD) or as its local NED position (PX4), as long as telemetry is fresh; the autopilot then keeps its
estimator fed while the spot is out of the camera's view (it descends vertically over it). A frame whose
target lies elsewhere does not move a committed spot either: the spot is sent instead, so the autopilot does
not chase a target that jumps between near-equal spots while it descends (measured in the closed loop,
docs/closed_loop.md). The spot is dropped when fresh evidence contradicts it, when telemetry goes stale, or
after ``hold_s`` seconds without confirmation, and the drop is announced; then a new spot can be committed.
Without a telemetry position (attitude and height above ground only) the same rules run in the frame the
images placed the vehicle in (fusion.result.ImagePlacement): image odometry's own frame, which drifts, or one
chained from the last telemetry position through a short gap. A spot there goes when that frame starts over or
the position comes back (``in_spot_frame``), and on a frame the images could not place; a target held from it
leaves as a body vector only (its local NED is not the autopilot's).
Pure numpy; the pipeline does the sending.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Optional, Tuple

import numpy as np

from edge_landing.runtime.core.camera import Mount
from edge_landing.runtime.core.messages import Target, VehicleState
from edge_landing.runtime.core.target_frames import aim_at_pose, aimed, target_ned
from edge_landing.runtime.fusion.grid import GridView
from edge_landing.runtime.fusion.result import ImagePlacement

log = logging.getLogger(__name__)
HELD = "held: committed spot from memory"
TELEMETRY_FRAME, CHAINED_FRAME, ODOMETRY_FRAME = "telemetry", "chained", "odometry"
SpotFrame = Tuple[str, int]       # (one of the three, the telemetry's position epoch or the odometry's number)


@dataclass(frozen=True)
class ContinuityConfig:
    """Seconds and metres."""

    commit_frames: int = 3        # a spot is committed after this many consecutive targets agree on it ...
    confirm_radius_m: float = 1.5  # ... within this distance (also what counts as confirming it later), or
    confirm_range_share: float = 0.1  # this share of the target's range when larger: a far spot's position
                                      # drifts with the metric scale (closed loop: 2.5-6 m at 50 m range) and
                                      # is confirmed, and refined, as the vehicle closes in
    hold_s: float = 20.0          # dropped after this long without a confirming target (not counting the time
                                  # the vehicle spends over it, see overhead_m)
    overhead_m: float = 3.0       # horizontally this close, the vehicle is over the spot: descending onto it
    cone_ratio: float = 2.0       # no new spot farther away horizontally than this × the height above it
    contradiction_radius_m: float = 1.0  # cells this close to the spot, observed in this frame, are the evidence:
    contradiction_frames: int = 10  # dropped when most of them are judged not landable this many frames in a row
                                    # (1 s at 10 frames/s), or all of them in one frame. Any one cell, or a majority
                                    # for 3 frames, was too strict: in the closed loop (docs/closed_loop.md) it
                                    # dropped ground-truth safe spots 7-8 times per landing as the view changed
    held_confidence: float = 0.5  # confidence factor of a target re-sent from memory
    min_clearance_m: float = 0.0  # the clearance fusion requires (0: the spot's own clearance)
    contradiction_range_m: float = 15.0  # farther than this, "not landable" near the spot is no evidence against
                                         # it: in the closed loop from 40 m the grid lost all clear ground
                                         # around ground-truth safe spots 15 times per landing at 45-65 m and
                                         # 14 times at 20-30 m, while every target it sent was safe
    # Only spots the drone's own motion confirmed are committed (ARCHITECTURE.md §11): a network-only target
    # (sent under --allow-unconfirmed) is passed on but never re-sent from memory, unless this is set too.
    commit_unconfirmed: bool = False


@dataclass(frozen=True)
class CommittedSpot:
    ned_m: np.ndarray
    clearance_m: float
    confidence: float
    confirmed_s: float            # capture time of the last target that confirmed it
    evidence: str = ""            # what vouched for it when it was last confirmed (Target.evidence)


class Continuity:
    def __init__(self, config: ContinuityConfig = ContinuityConfig(), mount: Optional[Mount] = None):
        """``mount``: the camera's, for the angles of a target held from memory (NaN without it)."""
        self.config = config
        self.mount = mount
        self.spot: Optional[CommittedSpot] = None
        self._candidate: Optional[np.ndarray] = None
        self._candidate_frames = 0
        self._contradicting_frames = 0
        self._last_step_s: Optional[float] = None
        self._frame: SpotFrame = (TELEMETRY_FRAME, 0)   # the frame the spot is kept in (see in_spot_frame)

    def drop(self) -> Optional[str]:
        """Forget the spot; returns an announcement when there was one."""
        had, self.spot, self._candidate, self._candidate_frames = self.spot, None, None, 0
        self._contradicting_frames = 0
        return "" if had is not None else None

    def step(self, target: Target, state: Optional[VehicleState], grid: Optional[GridView],
             reached_fusion: bool, placement: Optional[ImagePlacement] = None) -> Tuple[Target, str]:
        """The target to send for this frame and an announcement ('' when nothing to say).

        ``state`` is fresh telemetry at the capture time (None: not fresh, the spot is dropped);
        ``grid`` is this frame's grid (None when the frame did not reach it); ``reached_fusion`` is False for a
        frame that had no evidence at all (invalid frame or model fault): nothing is sent for it, nothing dropped;
        ``placement``: where the images placed a frame whose telemetry has no position (FusionResult.placement).
        """
        if state is None:
            return target, self._drop_said("telemetry not fresh")
        state, grid, frame = in_spot_frame(state, grid, placement)
        placed = frame[0] != TELEMETRY_FRAME
        moved = ""
        if frame != self._frame:
            # The autopilot's local frame moved (or the odometry's started over, or the spot's frame changed
            # between the two): the spot's NED point now names another place. The frame's own target was fused
            # in the new frame (fusion starts over on the same change): it is judged as any first target.
            old, self._frame = self._frame, frame
            moved = self._drop_said(_frame_change(old, frame))
        target, said = self._judge(target, state, grid, reached_fusion, placed)
        return target, moved or said

    def _judge(self, target: Target, state: VehicleState, grid: Optional[GridView], reached_fusion: bool,
               placed: bool) -> Tuple[Target, str]:
        """``step`` once the state is in the spot's frame (``placed``: the images' frame, see in_spot_frame)."""
        spot = self.spot
        if target.valid and spot is None:
            beyond = self._beyond_cone(target, state)
            if beyond:
                self._candidate, self._candidate_frames = None, 0
                return Target.none(target.frame_id, target.capture_time_s, beyond, target.timings_s), ""
        if target.valid and not (target.geometry_confirmed or self.config.commit_unconfirmed):
            return target, ""  # a network-only target (--allow-unconfirmed) is passed on, never committed
        if target.valid:
            said = self._observe(target, state)
            if spot is None or self.spot is not spot:  # nothing committed before, or it was confirmed just now
                return target, said
            elsewhere = target_ned(target, state)
            why = (f"chose a spot {float(np.linalg.norm(elsewhere[:2] - spot.ned_m[:2])):.1f} m away"
                   if elsewhere is not None else "its target has no position")
            target = Target.none(target.frame_id, target.capture_time_s, why, target.timings_s)
        if spot is None or not reached_fusion:
            self._last_step_s = target.capture_time_s
            return target, ""
        spot = self._pause_hold_overhead(spot, state, target.capture_time_s)
        age = target.capture_time_s - spot.confirmed_s
        if age > self.config.hold_s:
            return target, self._drop_said(f"not confirmed for {age:.0f} s")
        if grid is not None and self._contradicted(grid, spot, state):
            return target, self._drop_said("fresh evidence contradicts it")
        aim = aim_at_pose(spot.ned_m, state, spot.clearance_m, self.mount)
        if aim is None:
            return target, self._drop_said("no vehicle position to re-express it")
        held = aimed(Target(target.frame_id, target.capture_time_s, True,
                            f"{HELD} ({age:.1f} s; fusion: {target.reason})",
                            position_ned_m=None if placed else spot.ned_m.copy(),
                            clearance_m=spot.clearance_m, confidence=spot.confidence * self.config.held_confidence,
                            timings_s=target.timings_s, evidence=f"{spot.evidence} (held)" if spot.evidence else ""),
                     aim)
        return held, ""

    def in_telemetry_frame(self) -> bool:
        """Whether the committed spot's NED is the autopilot's local frame (not image odometry's)."""
        return self._frame[0] == TELEMETRY_FRAME

    def _beyond_cone(self, target: Target, state: VehicleState) -> str:
        """Why a new spot is not taken: farther than ``cone_ratio`` × the height above it (the autopilot flies to
        a target at its current height: low and far is a flight past whatever stands in between; in the closed
        loop a spot committed 45 m away at 8 m height flew the vehicle into a building). '' when it is taken."""
        ned = target_ned(target, state)
        position = state.position_ned_m
        if ned is None or position is None:
            return ""
        height_m = float(ned[2] - np.asarray(position)[2])
        away_m = float(np.hypot(*(ned[:2] - np.asarray(position)[:2])))
        if away_m <= self.config.cone_ratio * max(height_m, 0.0):
            return ""
        return f"held: spot {away_m:.0f} m away at {height_m:.0f} m height, beyond the {self.config.cone_ratio:g}:1 cone"

    def _pause_hold_overhead(self, spot: CommittedSpot, state: VehicleState, now_s: float) -> CommittedSpot:
        """The hold clock does not run while the vehicle is over the spot (within ``overhead_m`` horizontally):
        it descends onto a spot its camera cannot see from there, so no confirmation can come (ArduPilot descends
        only within PLND_XY_DIST_MAX = 2.5 m of the target)."""
        last, self._last_step_s = self._last_step_s, now_s
        position = state.position_ned_m
        if last is None or position is None or not 0 < now_s - last < 1.0:
            return spot
        if float(np.hypot(*(np.asarray(position)[:2] - spot.ned_m[:2]))) > self.config.overhead_m:
            return spot
        self.spot = replace(spot, confirmed_s=spot.confirmed_s + (now_s - last))
        return self.spot

    def _observe(self, target: Target, state: VehicleState) -> str:
        ned = target_ned(target, state)
        if ned is None:
            return ""
        range_m = float(target.range_m) if math.isfinite(target.range_m) else 0.0
        r = max(self.config.confirm_radius_m, self.config.confirm_range_share * range_m)
        if self.spot is not None:
            if float(np.linalg.norm(ned[:2] - self.spot.ned_m[:2])) <= r:  # confirmed: follow the fresh estimate
                self.spot = CommittedSpot(ned, target.clearance_m, target.confidence, target.capture_time_s, target.evidence)
            return ""  # elsewhere: the committed spot stays until it is dropped
        if self._candidate is not None and float(np.linalg.norm(ned[:2] - self._candidate[:2])) <= r:
            self._candidate_frames += 1
        else:
            self._candidate, self._candidate_frames = ned, 1
        if self._candidate_frames >= self.config.commit_frames:
            self.spot = CommittedSpot(ned, target.clearance_m, target.confidence, target.capture_time_s, target.evidence)
            self._candidate, self._candidate_frames = None, 0
        return ""

    def _contradicted(self, grid: GridView, spot: CommittedSpot, state: VehicleState) -> bool:
        """Fresh evidence against the spot: most cells near it, observed in this frame, judged not landable for
        ``contradiction_frames`` frames in a row, or all of them in one frame that saw the whole disc; and no
        landable ground with the clearance within the confirmation radius (else the grid only shows the patch
        displaced: a far spot moves with the metric scale as the height below the vehicle changes; in the
        closed loop this dropped ground-truth safe spots every few seconds). Only evidence from within
        ``contradiction_range_m`` counts, and only cells observed in this frame (the spot is out of view
        during the descent)."""
        position = state.position_ned_m
        range_m = 0.0 if position is None else float(np.linalg.norm(np.asarray(position) - spot.ned_m))
        shares = self._bad_share(grid, spot) if range_m <= self.config.contradiction_range_m else None
        if shares is None:
            return False  # not in view this frame, or too far: no evidence either way
        bad_share, seen_share = shares
        self._contradicting_frames = self._contradicting_frames + 1 if bad_share > 0.5 else 0
        # At once only on a full view: a spot half out of the image is seen by its edge rows, where depth is worst
        # (in the closed loop such single frames dropped ground-truth safe spots on the final approach).
        at_once = bad_share >= 1.0 and seen_share >= 0.9
        if not (at_once or self._contradicting_frames >= self.config.contradiction_frames):
            return False
        radius_m = max(self.config.confirm_radius_m, self.config.confirm_range_share * range_m)
        window = self._window(grid, spot, radius_m)
        if window is not None:
            (r0, r1, c0, c1), near = window
            need = self.config.min_clearance_m or spot.clearance_m
            clear = grid.landable[r0:r1, c0:c1] & (grid.clearance_m[r0:r1, c0:c1] >= need - 1e-6) & near
            if clear.any():
                log.debug("committed spot: the grid shows its patch displaced within %.1f m; kept", radius_m)
                return False
        log.info("committed spot: %.0f%% of the cells observed within %.1f m not landable for %d frames, no clear "
                 "ground within %.1f m", 100 * bad_share, self.config.contradiction_radius_m,
                 self._contradicting_frames, radius_m)
        return True

    @staticmethod
    def _window(grid: GridView, spot: CommittedSpot, radius_m: float
                ) -> Optional[Tuple[Tuple[int, int, int, int], np.ndarray]]:
        """The grid's cells around the spot: (row, column bounds) and the mask of those within ``radius_m``."""
        if grid.frame != "ned":
            return None
        n, e = float(spot.ned_m[0]), float(spot.ned_m[1])
        centre = grid.cell_of(n, e)
        if centre is None:
            return None
        k = int(math.ceil(radius_m / grid.cell_m))
        rows, cols = grid.shape
        r0, r1 = max(centre[0] - k, 0), min(centre[0] + k + 1, rows)
        c0, c1 = max(centre[1] - k, 0), min(centre[1] + k + 1, cols)
        north = grid.north0_m + (np.arange(r0, r1) + 0.5) * grid.cell_m
        east = grid.east0_m + (np.arange(c0, c1) + 0.5) * grid.cell_m
        near = np.hypot(north[:, None] - n, east[None, :] - e) <= radius_m
        return (r0, r1, c0, c1), near

    def _bad_share(self, grid: GridView, spot: CommittedSpot) -> Optional[Tuple[float, float]]:
        """Of the cells within the contradiction radius: the share of those observed in this frame that are not
        landable, and the share observed in this frame (None: less than half of them observed)."""
        window = self._window(grid, spot, self.config.contradiction_radius_m)
        if window is None:
            return None
        (r0, r1, c0, c1), near = window
        seen = grid.observed if grid.seen is None else grid.seen >= 1.0 - 1e-6   # seen is 1 where this frame saw
        fresh = seen[r0:r1, c0:c1] & near
        if np.count_nonzero(fresh) < 0.5 * np.count_nonzero(near):
            return None  # a sliver at the image's edge (where depth is worst) is not a view of the spot
        n_fresh = float(np.count_nonzero(fresh))
        return (float(np.count_nonzero(fresh & ~grid.landable[r0:r1, c0:c1])) / n_fresh,
                n_fresh / float(np.count_nonzero(near)))

    def _drop_said(self, why: str) -> str:
        if self.spot is None:
            self._candidate, self._candidate_frames = None, 0
            return ""
        self.drop()
        log.warning("committed landing spot dropped: %s", why)
        return f"spot dropped: {why}"


def in_spot_frame(state: VehicleState, grid: Optional[GridView], placement: Optional[ImagePlacement]
                  ) -> Tuple[VehicleState, Optional[GridView], SpotFrame]:
    """``state`` and fusion's ``grid`` in the frame a spot seen with them is kept in, and that frame: the
    telemetry's (its position epoch; both unchanged), or, for a frame without a telemetry position that the images
    placed, image odometry's own (numbered by the odometry) or one chained from a telemetry position by the images
    during a short gap; the vehicle is then where the images placed it and the vehicle-centred grid is moved there.
    A chained frame is apart from the telemetry's it came from: the position that comes back after a gap (dead
    reckoning, a GPS glitch) may have drifted by metres without a jump to say so, and a spot carried over would
    be re-expressed from it."""
    if state.position_ned_m is not None or placement is None:
        return state, grid, (TELEMETRY_FRAME, state.position_epoch)
    odometry = placement.odometry_epoch
    frame = (CHAINED_FRAME, state.position_epoch) if odometry is None else (ODOMETRY_FRAME, odometry)
    p = np.asarray(placement.position_ned_m, dtype=np.float64).reshape(3)
    if grid is not None and grid.frame == "vehicle":
        grid = replace(grid, frame="ned", north0_m=grid.north0_m + float(p[0]), east0_m=grid.east0_m + float(p[1]))
    return replace(state, position_ned_m=p.copy()), grid, frame


def _frame_change(old: SpotFrame, new: SpotFrame) -> str:
    if old[0] == new[0] == TELEMETRY_FRAME:
        return "position or heading jumped"
    if old[0] == new[0] == ODOMETRY_FRAME:
        return "image odometry started over"
    return "its frame changed (telemetry position and image odometry)"
