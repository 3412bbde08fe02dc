"""A live synthetic camera: frames of a landing flight, rendered on demand (for ``edge-run --camera sim``).

``read()`` returns (rgb uint8 H×W×3, Pose, VehicleState) like a camera with perfect telemetry; the flight
restarts when it ends (time keeps increasing). ``read_truth()`` also gives the ground truth.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional

import numpy as np

from edge_landing.runtime.core.camera import Intrinsics, Mount
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.geometry import HvoThresholds
from edge_landing.runtime.core.messages import VehicleState
from edge_landing.runtime.io.poses import Pose

from .effects import EffectOverrides
from .flight import VehicleSample
from .generate import SimConfig, pose_of, render_sample, vehicle_samples
from .render import Geometry, Renderer
from .world import Style, build_world


@dataclass(frozen=True)
class SimFrame:
    """One live frame with everything the simulator knows about it."""

    rgb: np.ndarray
    pose: Pose
    state: VehicleState
    geometry: Geometry


class SimCamera:
    """Synthetic camera flying a landing approach over a procedural world.

    ``realtime=True`` paces ``read()`` at ``fps`` like a real camera; otherwise frames come as fast as
    they render. Frame times (``Pose.t_s``, ``VehicleState.time_s``) are simulation seconds from 0.
    """

    def __init__(self, style: Style | str = Style.SUBURBAN, seed: int = 0, width: int = 320, height: int = 240,
                 fps: float = 10.0, flight_frames: int = 200, effects: EffectOverrides = EffectOverrides(),
                 realtime: bool = False, hfov_deg: float = 90.0):
        style = style if isinstance(style, Style) else Style.from_string(style)
        if flight_frames < 3:
            raise InputError(f"a sim camera flight needs at least 3 frames, got {flight_frames}")
        self.config = SimConfig(out=Path("."), frames=flight_frames, style=style, seed=int(seed), width=width,
                                height=height, hfov_deg=hfov_deg, effects=effects, flight=True, fps=fps)
        self.world = build_world(style, int(seed))
        self.mount = Mount()
        self.thresholds = HvoThresholds()
        self.renderer = Renderer(self.world, self.config.intrinsics, self.mount, self.thresholds, labels=self.config.labels)
        self._plan: list[VehicleSample] = list(vehicle_samples(self.config, self.world))   # same as edge-sim --flight
        self._index = 0
        self._start: Optional[float] = None
        self.realtime = realtime

    @property
    def intrinsics(self) -> Intrinsics:
        return self.config.intrinsics

    @property
    def fps(self) -> float:
        return self.config.fps

    def read_truth(self) -> SimFrame:
        k = self._index
        self._index += 1
        lap, i = divmod(k, len(self._plan))
        s = self._plan[i]
        t = s.t_s + lap * len(self._plan) / self.fps
        sample = VehicleSample(t, s.position_ned_m, s.attitude, s.agl_m)
        if self.realtime:
            if self._start is None:
                self._start = time.monotonic()
            delay = self._start + t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        r = render_sample(self.config, i, sample, self.renderer)
        pose = pose_of(k, sample)
        state = VehicleState(time_s=t, attitude=s.attitude, position_ned_m=s.position_ned_m.copy(), agl_m=s.agl_m,
                             agl_source="sim")
        return SimFrame(r.rgb, pose, state, r.geometry)

    def read(self) -> tuple[np.ndarray, Pose, VehicleState]:
        f = self.read_truth()
        return f.rgb, f.pose, f.state

    def __iter__(self) -> Iterator[tuple[np.ndarray, Pose, VehicleState]]:
        while True:
            yield self.read()

    def close(self) -> None:
        """Nothing to release; here so the camera can be used like the runtime's other frame sources."""
