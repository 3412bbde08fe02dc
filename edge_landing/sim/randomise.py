"""Domain randomisation of the camera (``edge-sim --randomise``): field of view, height, pitch, jitter.

The shipped EdgeNet saw one camera pose (45° down, 30-90 m, 90° HFOV) and learned it: its depth keeps
growing towards the top of the frame even on a nadir view. Randomised views break that prior:

- horizontal FOV: one draw per scene in ``hfov_deg`` (intrinsics are per scene in scene.json);
- camera pitch below the horizon: uniform in ``pitch_down_deg`` per frame, nadir (90°) included;
- height above the first surface below: uniform in ``agl_m`` per frame;
- roll/pitch jitter: Gaussian, ``jitter_deg`` standard deviation.

The mount in scene.json stays the default (45° down); the extra pitch is carried by the vehicle attitude in
poses.csv, so every consumer that composes mount and attitude (the runtime, edge-eval's landable figure)
sees the true camera orientation. Every draw comes from generators seeded by (seed, frame, purpose).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from edge_landing.runtime.core.camera import Attitude, Mount

from .flight import VIEW_REGION_HALF_M, VehicleSample
from .world import World


@dataclass(frozen=True)
class ViewRanges:
    """Ranges of the camera draws (degrees, metres)."""

    hfov_deg: tuple[float, float] = (60.0, 110.0)
    pitch_down_deg: tuple[float, float] = (20.0, 90.0)
    agl_m: tuple[float, float] = (10.0, 120.0)
    jitter_deg: float = 3.0

    def to_json(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


RANGES = ViewRanges()


def scene_hfov_deg(seed: int, ranges: ViewRanges = RANGES) -> float:
    """The scene's horizontal field of view, drawn once from the seed."""
    rng = np.random.default_rng([int(seed), 0xF0F])
    return round(float(rng.uniform(*ranges.hfov_deg)), 3)


def randomised_view(world: World, rng: np.random.Generator, t_s: float = 0.0, mount: Mount = Mount(),
                    ranges: ViewRanges = RANGES) -> VehicleSample:
    """A view with the camera ``pitch_down`` below the horizon: vehicle pitch = −pitch_down − mount pitch
    (mount pitch is negative below the horizon), plus jitter; roll is jitter only."""
    n, e = rng.uniform(-VIEW_REGION_HALF_M, VIEW_REGION_HALF_M, 2)
    yaw = rng.uniform(-math.pi, math.pi)
    agl = rng.uniform(*ranges.agl_m)
    pitch_down = math.radians(rng.uniform(*ranges.pitch_down_deg))
    jitter = np.radians(rng.normal(0.0, ranges.jitter_deg, 2))
    # Keep the camera at most 90° down (past nadir the image would turn upside down in pitch).
    cam_pitch = max(-pitch_down + float(jitter[1]), -math.pi / 2)
    pitch = cam_pitch - mount.pitch_rad
    z = float(world.surface_z(np.array([n]), np.array([e]))[0]) - agl
    return VehicleSample(float(t_s), np.array([n, e, z]), Attitude(float(jitter[0]), pitch, float(yaw)), float(agl))
