"""What fusion hands to the next stages: the target and the grid it was chosen on (ARCHITECTURE.md §6)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from edge_landing.runtime.core.messages import Target
from edge_landing.runtime.fusion.grid import GridView
from edge_landing.runtime.fusion.motion_grid import GeometryView
from edge_landing.runtime.fusion.mount_check import MountEstimate


@dataclass(frozen=True)
class ImagePlacement:
    """Where the motion stage placed a frame that came without a telemetry position (fusion.odometry): the
    vehicle's local NED in image odometry's own frame number ``odometry_epoch``, or, with ``odometry_epoch``
    None, in the telemetry's frame (chained from a telemetry position seconds ago: a short dropout). The
    continuity of ARCHITECTURE.md §12 keeps a committed spot in this frame; nothing in it is sent as a local
    NED position (the autopilot's frame is another)."""

    position_ned_m: np.ndarray
    odometry_epoch: Optional[int]


@dataclass(frozen=True)
class FusionResult:
    """One frame's fusion output. ``grid`` is the snapshot judged for this frame, or None when this frame did
    not reach the grid (invalid prediction, stale frame, ...); readers never reach into the fuser for it.
    ``geometry``: the motion-geometry evidence on the same cells (ARCHITECTURE.md §11), or None. ``mount``: the
    camera's orientation measured from the images so far (fusion.mount_check), or None while too few pairs agree.
    ``placement``: where the images placed a frame without a telemetry position (None: it had one, or the
    images could not place it)."""

    target: Target
    grid: Optional[GridView] = None
    geometry: Optional[GeometryView] = None
    mount: Optional[MountEstimate] = None
    placement: Optional[ImagePlacement] = None
