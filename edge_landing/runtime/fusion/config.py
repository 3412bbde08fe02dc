"""Fusion's settings (ARCHITECTURE.md §6, §11): one frozen dataclass, checked on construction."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.fusion.deferred import StageTiming
from edge_landing.runtime.fusion.motion import MotionConfig
from edge_landing.runtime.fusion.mount_check import MountCheckConfig

_MAX_GRID_CELLS = 4096                 # cells across the fusion grid


@dataclass(frozen=True)
class FusionConfig:
    """Fusion settings. Lengths in metres, angles in radians, times in seconds."""

    working_hw: tuple[int, int] = (120, 160)                # (height, width) depth and HVO are resized to
    cell_m: float = 0.5                           # grid cell size
    grid_radius_m: float = 50.0                   # half-width of the square grid around the vehicle
    vehicle_radius_m: float = 1.0
    margin_m: float = 1.0                         # a candidate needs clearance >= radius + margin
    min_points_per_cell: float = 1.0              # support: (decayed) footprint samples per cell
    max_height_spread_m: float = 0.1              # std of heights in a cell
    # Flat by depth, per pixel. 15°, not the labels' 10°: per-pixel normals of a network's depth scatter (the
    # suburban+urban EdgeNet's median slope on truly level ground is ~20° before cell voting); the cell height
    # spread, P(horizontal) and the vote still decide. With 10° the default sim flight got 9/200 targets, with
    # 15° 165/200, all on ground-truth level ground with the clearance (benchmarks/landing_truth.py).
    max_slope_rad: float = math.radians(15.0)
    min_horizontal_share: float = 0.6             # mean P(horizontal) in a cell
    min_flat_share: float = 0.9                   # share of samples flat by depth in a cell
    min_vote_share: float = 0.6                   # NED: decayed share of frames that judged a cell landable
    clearance_saturation_m: float = 4.0           # more clearance than this earns no more score
    travel_penalty_per_m: float = 0.03            # score (metres of clearance) lost per metre of travel
    hysteresis_m: float = 1.0                     # a new spot must beat the kept one by this score
    decay_s: float = 2.0                          # e-folding time of grid evidence (NED mode)
    memory_s: float = 3.0                         # NED: a cell not observed for this long is unobserved again
    stale_after_s: float = 0.5                    # frames older than this (vs now_s) give no target
    keep_target_s: float = 2.0                    # forget the kept target after this long without one
    splat_spacing_m: float = 0.5                  # sample spacing inside a pixel's footprint
    max_footprint_m: float = 4.0                  # larger pixel steps are depth discontinuities
    max_samples_per_axis: int = 4
    min_neighbours_to_fill: int = 6               # an empty cell with this many observed of 8 is filled (9: off)
    depth_smoothing_px: int = 3                   # box filter on depth before normals (1: off) ...
    smoothing_max_step: float = 0.05              # ... except across steps > this share of the depth
    min_valid_depth_share: float = 0.05           # less valid depth than this: no target
    depth_only_confidence: float = 0.5            # confidence factor without HVO
    obstacle_height_m: float = 0.5                # geometry must be able to see obstacles this tall to confirm
    geometry_memory_s: float = 30.0               # how long a geometry confirmation holds (hover, descent)
    geometry_interval_s: float = 0.2              # the motion stage runs at most this often (0: every frame)
    # Inline: a frame's own pair is measured before its spot is chosen. Overlapped (edge-run's default): on a
    # thread while the next frame is inferred, collected by the next fused frame (fusion.deferred); with a
    # telemetry position only (without one, the frame's place in the grid comes from the stage).
    geometry_timing: StageTiming = StageTiming.INLINE
    allow_unconfirmed: bool = False               # send network-only spots when geometry cannot confirm
    # Opt-in (fusion.focus): the motion stage's window skips candidate spots within this many metres of an
    # obstacle geometry saw (negative: off). Off by default: false obstacle marks also move the window off ground
    # that measuring again would confirm (docs/MEASUREMENTS.md, "Where geometry looks").
    focus_skip_obstacles_m: float = -1.0
    confirm_on_horizontal: bool = True            # geometry-clear cells HVO calls horizontal may be confirmed
                                                  # without the depth flatness tests (fusion.confirm, §11)
    # A confirmed spot whose level by the network's depth is farther than this from the level motion geometry
    # measured there is placed at geometry's (the network's depth at a grazing angle can be tens of metres off).
    max_level_disagreement_m: float = 2.0
    motion: MotionConfig = MotionConfig()
    mount_check: MountCheckConfig = MountCheckConfig()   # the camera's orientation against the images

    def __post_init__(self) -> None:
        h, w = self.working_hw
        if h < 8 or w < 8:
            raise InputError(f"fusion working size must be at least 8x8 pixels, got {h}x{w}")
        positive = {"cell_m": self.cell_m, "grid_radius_m": self.grid_radius_m,
                    "splat_spacing_m": self.splat_spacing_m, "decay_s": self.decay_s,
                    "stale_after_s": self.stale_after_s, "memory_s": self.memory_s, "max_footprint_m": self.max_footprint_m,
                    "clearance_saturation_m": self.clearance_saturation_m,
                    "max_samples_per_axis": self.max_samples_per_axis}
        for name, value in positive.items():
            if not value > 0:
                raise InputError(f"fusion {name} must be > 0, got {value}")
        if self.grid_radius_m < 2 * self.required_clearance_m:
            raise InputError(f"fusion grid_radius_m={self.grid_radius_m} is too small for a clearance of "
                             f"{self.required_clearance_m} m (expected at least twice that)")
        cells = math.ceil(2.0 * self.grid_radius_m / self.cell_m)
        if cells > _MAX_GRID_CELLS:
            # (fusion.grid indexes a frame's cells in float32: exact below 2^24 = 4096² cells)
            raise InputError(f"fusion grid_radius_m={self.grid_radius_m} with cell_m={self.cell_m} gives {cells} cells "
                             f"across; at most {_MAX_GRID_CELLS}")
        if self.vehicle_radius_m < 0 or self.margin_m < 0 or self.travel_penalty_per_m < 0 or self.hysteresis_m < 0:
            raise InputError("fusion vehicle_radius_m, margin_m, travel_penalty_per_m and hysteresis_m must be >= 0")
        if self.depth_smoothing_px < 1 or self.depth_smoothing_px % 2 == 0:
            # an even box has no centre pixel: it would shift the depth by half a pixel
            raise InputError(f"fusion depth_smoothing_px must be odd and >= 1, got {self.depth_smoothing_px}")
        if not 1 <= self.min_neighbours_to_fill <= 9:
            raise InputError(f"fusion min_neighbours_to_fill must be in 1..9, got {self.min_neighbours_to_fill}")
        if not 0 < self.min_vote_share <= 1:
            raise InputError(f"fusion min_vote_share must be in (0, 1], got {self.min_vote_share}")
        if not 0 < self.max_slope_rad < math.pi / 2:
            raise InputError(f"fusion max_slope_rad must be in (0, pi/2), got {self.max_slope_rad}")
        if not self.geometry_interval_s >= 0:
            raise InputError(f"fusion geometry_interval_s must be >= 0, got {self.geometry_interval_s}")
        if not -math.inf < self.focus_skip_obstacles_m <= self.grid_radius_m:
            raise InputError(f"fusion focus_skip_obstacles_m must be a finite number up to grid_radius_m "
                             f"(negative: off), got {self.focus_skip_obstacles_m}")
        if not self.obstacle_height_m > 0 or not self.geometry_memory_s > 0:
            raise InputError(f"fusion obstacle_height_m and geometry_memory_s must be > 0, got "
                             f"{self.obstacle_height_m} and {self.geometry_memory_s}")

    @property
    def required_clearance_m(self) -> float:
        return self.vehicle_radius_m + self.margin_m

    def horizontal_share_to_confirm(self, use_hvo: bool) -> Optional[float]:
        """The mean P(horizontal) at which an observed cell counts as one the network does not object to
        (GridView.allowed_in), or None where only landable cells do (no HVO head, or confirm_on_horizontal off)."""
        return self.min_horizontal_share if use_hvo and self.confirm_on_horizontal else None
