"""Geometry confirmation for fusion: the motion stage, its NED evidence grid, and what it says about a spot.

The network may propose, only geometry may confirm (ARCHITECTURE.md §11). With the camera image, the vehicle
position and its height above ground, the motion stage (fusion.motion) measures heights above the ground
from frame pairs and the evidence is kept per cell in local NED (fusion.motion_grid), aligned cell for cell
with fusion's grid. The stage runs at most every ``geometry_interval_s`` (evidence is kept for
``geometry_memory_s`` anyway; a pair every 0.2 s loses nothing a landing needs and halves the cost).
Pure numpy/OpenCV, no I/O; memory bounded by the grid and the stage's keyframe ring.
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING, Optional

import numpy as np

from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount
from edge_landing.runtime.core.messages import EVIDENCE_GEOMETRY, VehicleState
from edge_landing.runtime.fusion.grid import GridView, clearance_from_mask
from edge_landing.runtime.fusion.landing import Choice
from edge_landing.runtime.fusion.motion import CameraPose, MotionStage
from edge_landing.runtime.fusion.motion_grid import GeometryGrid, GeometryView

if TYPE_CHECKING:
    from edge_landing.runtime.fusion.config import FusionConfig


class GeometryConfirmation:
    """Per-stream geometry evidence: ``run`` once per fused frame, then ask about spots on that frame's grid."""

    def __init__(self, config: FusionConfig, intrinsics: Intrinsics, mount: Mount):
        self.config = config
        self.mount = mount
        self.motion = MotionStage(config.motion, intrinsics, mount)
        self.grid = GeometryGrid(config.cell_m, config.grid_radius_m, config.geometry_memory_s,
                                 config.obstacle_height_m, config.motion.detect_sigmas)
        self.view: Optional[GeometryView] = None
        self.note = ""
        self._last_run_s: Optional[float] = None

    def reset(self) -> None:
        self.grid.clear()
        self.motion.reset()
        self.view, self.note, self._last_run_s = None, "", None

    def run(self, view: Optional[GridView], image: Optional[np.ndarray], state: Optional[VehicleState],
            position: Optional[np.ndarray], t_cap: float, focus: Optional[np.ndarray]) -> Optional[GeometryView]:
        """Run the motion stage on this frame (its window centred on the network's candidate ``focus``, NED)
        when due, and return the evidence aligned with the fusion grid ``view`` (or None)."""
        self.view = None
        if view is None or position is None:
            self.note = "no vehicle position (geometry needs telemetry poses)"
            return None
        self.grid.centre_on(float(position[0]), float(position[1]))
        agl = None if state is None else state.agl_m
        last = self._last_run_s
        if image is None or agl is None or not math.isfinite(float(agl)):
            self.note = "no camera image for geometry" if image is None else "no height above ground"
        elif last is not None and 0.0 <= t_cap - last < self.config.geometry_interval_s - 1e-3:
            self.note = f"no new geometry (the stage runs every {self.config.geometry_interval_s:g} s)"
        else:
            self._last_run_s = t_cap
            pose = CameraPose.of(self.mount, state.attitude if state else Attitude(), position, float(agl))
            result = self.motion.update(np.asarray(image), pose, t_cap, focus)
            if result is not None:
                self.grid.add(result)
                self.note = ""
            else:
                self.note = f"no new geometry ({self.motion.last_reason})"
        self.view = self.grid.view(view.north0_m, view.east0_m, (int(view.shape[0]), int(view.shape[1])), t_cap)
        return self.view

    def confirmed_view(self, view: GridView) -> GridView:
        """``view`` with only the cells that are network-landable and geometry-clear (clearance recomputed)."""
        landable = view.landable if self.view is None else view.landable & self.view.clear
        return replace(view, landable=landable, clearance_m=clearance_from_mask(landable, view.cell_m))

    def evidence(self) -> str:
        return EVIDENCE_GEOMETRY if not self.note else f"{EVIDENCE_GEOMETRY}; {self.note}"

    def unconfirmed_reason(self, proposal: Choice, view: Optional[GridView], position: Optional[np.ndarray]) -> str:
        """Why the network's spot is not sent: what geometry knows about its cell, and the best confirmed disc."""
        cfg, geo = self.config, self.view
        if geo is None or view is None or position is None:
            return f"unconfirmed: {self.note}"
        cell = view.cell_of(proposal.north_m, proposal.east_m)
        if cell is None:
            return "unconfirmed: spot outside the geometry grid"
        best = float(self.confirmed_view(view).clearance_m.max())
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

    def figures(self, choice: Choice, view: Optional[GridView]) -> tuple[float, float, float]:
        """(baseline, detectable height, age of confirmation) of the spot's geometry cell (NaN without)."""
        geo = self.view
        cell = None if geo is None or view is None else view.cell_of(choice.north_m, choice.east_m)
        if cell is None or geo is None:
            return math.nan, math.nan, math.nan
        return float(geo.baseline_m[cell]), float(geo.detectable_m[cell]), float(geo.clear_age_s[cell])
