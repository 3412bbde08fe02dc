"""Geometry confirmation for fusion: the motion stage, its NED evidence grid, and what it says about a spot.

The network may propose, only geometry may confirm (ARCHITECTURE.md §11). With the camera image, the vehicle
position and its height above ground, the motion stage (fusion.motion) measures heights above the ground
from frame pairs and the evidence is kept per cell in local NED (fusion.motion_grid), aligned cell for cell
with fusion's grid. The stage runs at most every ``geometry_interval_s`` (evidence is kept for
``geometry_memory_s`` anyway; a pair every 0.2 s loses nothing a landing needs and halves the cost).
Without a telemetry position (attitude and height above ground only) the stage places frames by the image-only
pose (fusion.image_motion); the grid then lives in the image odometry's frame, offset onto fusion's
vehicle-centred grid (the same cells up to half a cell; obstacles are grown by a metre), with a memory of the
keyframe ring only (the odometry drifts), and evidence says ``baseline from image pose``. A position missing
for less than the ring's span is chained from the last telemetry position and stays in this grid.
With ``FusionConfig.geometry_timing`` overlapped, a due frame hands its stage run to a thread and the next
fused frame adds the result (fusion.deferred): the stage's own state is touched only inside the run, and what
the frame needs of it comes back in a ``_StageOutcome``.
Pure numpy/OpenCV, no I/O; memory bounded by the grid, the stage's keyframe ring and one run in flight.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import partial
from typing import TYPE_CHECKING, Callable, Optional

import cv2
import numpy as np

from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount
from edge_landing.runtime.core.messages import EVIDENCE_GEOMETRY, EVIDENCE_IMAGE_POSE, VehicleState
from edge_landing.runtime.fusion.deferred import DeferredRun, Done, StageTiming
from edge_landing.runtime.fusion.focus import KnownObstacles
from edge_landing.runtime.fusion.grid import GridView, clearance_from_mask
from edge_landing.runtime.fusion.image_motion import ImagePose
from edge_landing.runtime.fusion.landing import Choice
from edge_landing.runtime.fusion.motion import POSE_IMAGE, POSE_TELEMETRY, CameraPose, MotionStage, ParallaxResult
from edge_landing.runtime.fusion.motion_grid import GeometryGrid, GeometryView
from edge_landing.runtime.fusion.mount_check import MountCheck, MountEstimate
from edge_landing.runtime.fusion.result import ImagePlacement
from edge_landing.runtime.fusion.verdicts import NetworkVerdicts

if TYPE_CHECKING:
    from edge_landing.runtime.fusion.config import FusionConfig


@dataclass(frozen=True)
class _StageOutcome:
    """What one motion-stage update left for the main thread (read there, never from the stage itself, which
    may be measuring the next frame on its thread)."""

    result: Optional[ParallaxResult]
    reason: str                             # the stage's last_reason
    frame: tuple[str, int]                  # pose source and odometry epoch the result is in
    image_posed: bool                       # the frame had no telemetry position: placed by the images
    image_pose: Optional[ImagePose]         # the image-only estimate then (None: none yet)
    mount_checked: bool                     # the mount check took a pair and estimated again ...
    mount_estimate: Optional[MountEstimate]  # ... this (None: not enough agreement yet)
    position_ned_m: Optional[np.ndarray]    # where the images placed a frame without position (None: not placed)


def _placement(out: _StageOutcome) -> Optional[ImagePlacement]:
    """Where a stage run placed its frame without a telemetry position, in the frame of its evidence."""
    p = out.position_ned_m
    if p is None or not np.all(np.isfinite(p)):
        return None
    return ImagePlacement(p.copy(), out.frame[1] if out.frame[0] == POSE_IMAGE else None)


class GeometryConfirmation:
    """Per-stream geometry evidence: ``run`` once per fused frame, then ask about spots on that frame's grid."""

    def __init__(self, config: FusionConfig, intrinsics: Intrinsics, mount: Mount):
        self.config = config
        self.mount = mount
        self.motion = MotionStage(config.motion, intrinsics, mount)
        self.grid = GeometryGrid(config.cell_m, config.grid_radius_m, config.geometry_memory_s,
                                 config.obstacle_height_m, config.motion.detect_sigmas)
        self.mount_check = MountCheck(config.mount_check, self.motion.k_cv, mount)
        self.mount_estimate: Optional[MountEstimate] = None   # the camera's orientation from the images so far
        self.verdicts = NetworkVerdicts(config.geometry_memory_s)  # the network's last look at each NED cell
        self.view: Optional[GeometryView] = None
        self.note = ""
        self.ran = False                                      # the last ``run`` ran (or handed over) the stage
        self.last: Optional[_StageOutcome] = None             # the newest stage outcome added to the grid
        self.placement: Optional[ImagePlacement] = None       # where the last ``run`` placed a frame without position
        self.stage_s = math.nan           # how long the stage run added this frame took (NaN: none added)
        self._runner: DeferredRun[_StageOutcome] = DeferredRun(config.geometry_timing, "geometry")
        self._last_run_s: Optional[float] = None
        self._frame: tuple[str, int] = (POSE_TELEMETRY, 0)   # pose source and odometry epoch of ``grid``
        self._known: Optional[KnownObstacles] = None         # obstacles of the last view, in local NED

    def reset(self) -> None:
        self._runner.cancel()           # before the stage's state goes: a job in flight still uses it
        self.grid.clear()
        self.verdicts.clear()
        self.motion.reset()
        self.mount_check.reset()
        self.mount_estimate = None
        self.view, self.note, self._last_run_s, self.ran, self.last = None, "", None, False, None
        self.placement, self._known = None, None

    def begin_frame(self) -> None:
        """A new fused frame: the stage has not run for it (yet)."""
        self.ran = False

    def run(self, view: Optional[GridView], image: Optional[np.ndarray], state: Optional[VehicleState],
            position: Optional[np.ndarray], t_cap: float,
            focus: Optional[Callable[[], Optional[np.ndarray]]]) -> Optional[GeometryView]:
        """Run the motion stage on this frame (its window centred on one of the network's candidate spots
        ``focus()``, K×3 NED, the first preferred; see fusion.focus) when due, and return the evidence
        aligned with the fusion grid ``view`` (or None). ``focus`` is called only when the stage runs: the
        candidates cost a pass over the grid that most frames (between runs) do not need.

        Overlapped (FusionConfig.geometry_timing), a stage run handed over by an earlier frame is collected
        first, and this frame's run is handed to a thread: its evidence reaches the next fused frame."""
        self.view, self.ran, self.stage_s, self.placement, self._known = None, False, math.nan, None, None
        collected = self._runner.pending
        if collected:
            self._apply(self._runner.collect())
        agl = math.nan if state is None or state.agl_m is None else float(state.agl_m)
        if view is None or (position is None and (image is None or not math.isfinite(agl))):
            self.note = "no vehicle position and no image pose (needs the camera image and height above ground)"
            return None
        last = self._last_run_s
        if image is None or not math.isfinite(agl):
            self.note = "no camera image for geometry" if image is None else "no height above ground"
        elif position is not None and last is not None and 0.0 <= t_cap - last < self.config.geometry_interval_s - 1e-3:
            # (Without position it runs every frame: the frame's place in the grid comes from the stage.)
            if not collected:
                self.note = f"no new geometry (the stage runs every {self.config.geometry_interval_s:g} s)"
        else:
            self._last_run_s, self.ran = t_cap, True
            self._submit(np.asarray(image), state, position, agl, t_cap, focus)
            if position is None or self._runner.timing is StageTiming.INLINE:
                done = self._runner.collect()
                self._apply(done)
                if position is None and done is not None:
                    self.placement = _placement(done.value)
            elif not collected:
                self.note = "no new geometry (this frame's pair is measured while the next frame is inferred)"
        # Without a position the stage ran inline above: this frame's placement is where the images put it.
        origin = position
        if origin is None and self.placement is not None:
            origin = self.placement.position_ned_m
        if origin is None:
            return None
        self.grid.centre_on(float(origin[0]), float(origin[1]))
        north0, east0 = view.north0_m, view.east0_m
        if position is None:           # fusion's grid is around the vehicle, this one in the odometry's frame
            north0, east0 = north0 + float(origin[0]), east0 + float(origin[1])
        self.view = self.grid.view(north0, east0, (int(view.shape[0]), int(view.shape[1])), t_cap)
        if position is not None:       # (in the odometry's frame the cells are not the next frame's cells)
            self._known = KnownObstacles(self.view.obstacle, north0, east0)
        return self.view

    def known_obstacles(self) -> Optional[KnownObstacles]:
        """Where the last frame's geometry evidence saw obstacles, in local NED (None: no evidence, or no
        telemetry position): for fusion.focus, before this frame's :meth:`run`."""
        return self._known

    def _submit(self, image: np.ndarray, state: Optional[VehicleState], position: Optional[np.ndarray], agl: float,
                t_cap: float, focus: Optional[Callable[[], Optional[np.ndarray]]]) -> None:
        """Hand one motion-stage update to the runner (inline: it runs now). ``focus`` is called by the job: the
        network's grid view it reads is a snapshot (fusion.grid), so a thread may read it."""
        if position is None and focus is not None:
            last, spots = self.motion.position_ned_m, focus()
            # The window follows the spot in the odometry's frame (a frame late is fine).
            if spots is None:
                focus = None
            else:
                focus = (lambda: spots + last) if last is not None else (lambda: spots)
        mount = state.mount_of(self.mount) if state else self.mount
        pos = position if position is not None else np.full(3, np.nan)   # the stage estimates it from the images
        pose = CameraPose.of(mount, state.attitude if state else Attitude(), pos, agl)
        # The camera's orientation against the images (fusion.mount_check): a fixed mount only (a gimbal's is
        # reported per frame), with telemetry positions.
        yaw = state.attitude.yaw_rad if position is not None and state is not None and state.camera_mount is None \
            else None
        # The frame's own copy: the caller may draw on or reuse its buffer while the stage reads it on a thread. In
        # colour when the stage checks colour (fusion.chroma).
        keep = image.ndim == 2 or self.motion.config.residual.colour
        frame = image.copy() if keep else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        self._runner.submit(partial(self._stage, frame, pose, t_cap, focus, position is not None, yaw))

    def _stage(self, frame: np.ndarray, pose: CameraPose, t_cap: float, focus: Optional[Callable[[], Optional[np.ndarray]]],
               has_position: bool, yaw_rad: Optional[float]) -> _StageOutcome:
        """The candidate spots, the motion stage's update and the mount check; touches only the stage's and the
        check's state."""
        motion = self.motion
        result = motion.update(frame, pose, t_cap, None if focus is None else focus())
        anchored = has_position or motion.anchored                  # in the telemetry's frame
        checked = yaw_rad is not None and self.mount_check.due(t_cap) and self.mount_check.add(motion.keyframes, yaw_rad)
        estimate = self.mount_check.estimate() if checked else None
        placed = None if has_position or motion.position_ned_m is None else motion.position_ned_m.copy()
        return _StageOutcome(result, motion.last_reason, (POSE_TELEMETRY, 0) if anchored else (POSE_IMAGE, motion.odometry_epoch),
                             not has_position, None if has_position else motion.image_pose, checked, estimate, placed)

    def _apply(self, done: Optional[Done[_StageOutcome]]) -> None:
        """Add a collected stage outcome to the evidence grid."""
        if done is None:
            return
        out, self.last, self.stage_s = done.value, done.value, done.run_s
        if out.frame != self._frame:
            # Image odometry drifts (about 1 % of the distance flown on the sim flights): its evidence is kept
            # only as long as the keyframe ring (motion.history_s), instead of geometry_memory_s.
            cfg, anchored = self.config, out.frame[0] == POSE_TELEMETRY
            memory = cfg.geometry_memory_s if anchored else min(cfg.geometry_memory_s, cfg.motion.history_s)
            self.grid = GeometryGrid(cfg.cell_m, cfg.grid_radius_m, memory, cfg.obstacle_height_m,
                                     cfg.motion.detect_sigmas)
            self._frame = out.frame
        self.note = "" if out.result is not None else f"no new geometry ({out.reason})"
        if out.result is not None:
            self.grid.add(out.result)
        if out.mount_checked:
            self.mount_estimate = out.mount_estimate

    def confirmed_view(self, view: GridView, use_hvo: bool = True) -> GridView:
        """``view`` with only the cells that geometry confirmed clear and the network does not object to
        (clearance recomputed).

        Not objecting: network-landable, or, with an HVO head and ``confirm_on_horizontal``, observed and
        horizontal by HVO (the surface's class: slopes, walls, vegetation). The network's own flatness tests
        (depth slope, height spread of 0.1 m) are left to geometry there: at 60-90 m range the network's depth
        spread fails on most open ground (measured: a 2 m landable disc on few frames of hazard-rich flights),
        while geometry measured the cell to the obstacle height. A network that objects to nothing (the
        flat-lying model of benchmarks/lying_model.py) leaves geometry alone, which stayed all safe there.
        In local NED, a cell the camera no longer sees keeps the network's verdict of its last look for as long
        as geometry's own memory (fusion.verdicts): the camera looks ahead, geometry clears ground late.
        Call once per frame, after :meth:`run`: it records this frame's verdicts."""
        if self.view is None:
            return view
        now, clear = self.view.time_s, self.view.clear
        ned = view.frame == "ned" and self._frame[0] == POSE_TELEMETRY
        # One box for this frame's verdicts (every observed cell) and for confirmation (every clear cell).
        x, y, w, h = cv2.boundingRect((view.observed | clear if ned else clear).view(np.uint8))
        landable = np.zeros(clear.shape, dtype=bool)
        if w == 0:
            if not ned:
                self.verdicts.clear()
            return replace(view, landable=landable, clearance_m=clearance_from_mask(landable, view.cell_m))
        win = (slice(y, y + h), slice(x, x + w))
        allowed = view.allowed_in(win, self.config.horizontal_share_to_confirm(use_hvo))
        if ned:
            self.verdicts.update(view, win, allowed, now)
            # (where fusion's grid still holds the cell's decayed sums: its level and shares)
            allowed = allowed | (self.verdicts.allowed_in(win, now) & (view.sums[0][win] > 0))
        else:
            self.verdicts.clear()
        landable[win] = allowed & clear[win]
        return replace(view, landable=landable, clearance_m=clearance_from_mask(landable, view.cell_m))

    def evidence(self) -> str:
        out = EVIDENCE_GEOMETRY
        stage = self.last
        if stage is not None and stage.image_posed:
            est = stage.image_pose
            sigma = f" ±{est.sigma_m:.2f} m" if est is not None and est.ok else ""
            out = f"{out}; {EVIDENCE_IMAGE_POSE}{sigma}"
        last = None if stage is None else stage.result
        if last is not None and last.rain_share > 0:
            out = f"{out}; rain streaks taken out ({100 * last.rain_share:.0f} % of the window)"
        if last is not None and last.plane_raised_m > 0:
            out = f"{out}; measured on a surface {last.plane_raised_m:.1f} m above the ground (a roof)"
        return out if not self.note else f"{out}; {self.note}"

    def verdict_note(self, choice: Choice, view: Optional[GridView]) -> str:
        """For the evidence: when the network no longer sees the chosen spot's cell, how old its verdict is."""
        geo = self.view
        cell = None if view is None or geo is None else view.cell_of(choice.north_m, choice.east_m)
        if cell is None or view is None or geo is None:
            return ""
        r, c = cell
        if view.observed_in((slice(r, r + 1), slice(c, c + 1)))[0, 0]:
            return ""
        age = self.verdicts.age_s(cell, geo.time_s)
        return f"; out of the network's view now (its last look {age:.1f} s ago)" if math.isfinite(age) else ""

    def unconfirmed_reason(self, proposal: Choice, view: Optional[GridView], confirmed: Optional[GridView]) -> str:
        """Why the network's spot is not sent: what geometry knows about its cell, and the best confirmed disc.

        ``confirmed`` is this frame's :meth:`confirmed_view` of ``view`` (None when geometry had no view)."""
        cfg, geo = self.config, self.view
        if geo is None or view is None or confirmed is None:
            return f"unconfirmed: {self.note}"
        cell = view.cell_of(proposal.north_m, proposal.east_m)
        if cell is None:
            return "unconfirmed: spot outside the geometry grid"
        best = float(confirmed.clearance_m.max())
        tail = f"; best confirmed clearance {best:.1f} m < {cfg.required_clearance_m:.1f} m"
        tail += f" ({self.note})" if self.note else ""
        if geo.obstacle[cell]:
            return f"unconfirmed: geometry sees an obstacle >= {cfg.obstacle_height_m:.1f} m at the network's spot{tail}"
        det = float(geo.detectable_m[cell])
        if not math.isfinite(det):
            return f"unconfirmed: geometry has not measured the spot yet{tail}"
        if det > cfg.obstacle_height_m:
            return (f"unconfirmed: geometry detects {det:.2f} m > {cfg.obstacle_height_m:.2f} m there "
                    f"(baseline too short for the range){tail}")
        return f"unconfirmed: geometry not clear around the spot (clearance){tail}"

    def _cell(self, choice: Choice, view: Optional[GridView]) -> Optional[tuple[int, int]]:
        """The spot's cell in the geometry view (None without one)."""
        return None if self.view is None or view is None else view.cell_of(choice.north_m, choice.east_m)

    def level_m(self, choice: Choice, view: Optional[GridView]) -> float:
        """NED down of the surface that confirmed the spot's geometry cell, as measured there (NaN without)."""
        geo, cell = self.view, self._cell(choice, view)
        return math.nan if cell is None or geo is None or not geo.clear[cell] else float(geo.clear_down_m[cell])

    def figures(self, choice: Choice, view: Optional[GridView]) -> tuple[float, float, float]:
        """(baseline, detectable height, age of confirmation) of the spot's geometry cell (NaN without)."""
        geo, cell = self.view, self._cell(choice, view)
        if cell is None or geo is None:
            return math.nan, math.nan, math.nan
        return float(geo.baseline_m[cell]), float(geo.detectable_m[cell]), float(geo.clear_age_s[cell])
