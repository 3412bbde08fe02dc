"""Vehicle poses: random benchmark views and a landing flight (approach, hover, descent).

The approach is straight by default. ``Approach.ARC`` bends it sideways (up to ``ARC_OFFSET_M`` at mid-way,
back on the line at its end) with the camera kept turned towards the spot: the direction of flight, and with it
the epipolar lines the motion stage measures along, turns by up to about 35° during the approach. A straight
approach keeps one direction, so an edge lying along it (a kerb, a shadow, a low wall along the flight) is seen
sliding along itself by every pair and can never be confirmed clear (fusion.image_checks).

Heights: ``agl_m`` is the distance straight down from the vehicle to the first surface (what a downward
rangefinder reads), so a view above a roof is 30–90 m above that roof. The vehicle flies level for random
views (roll = pitch = 0; the camera's 45° comes from the mount), and tilts a little while manoeuvring in a
flight, which the runtime must undo with the attitude.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from edge_landing.runtime.core.camera import Attitude
from edge_landing.runtime.core.choices import ChoiceEnum

from .world import World

VIEW_REGION_HALF_M = 150.0
AGL_RANGE_M = (30.0, 90.0)
PLAUSIBLE_SPEED_MPS = 25.0   # beyond what a multirotor landing camera flies
ARC_OFFSET_M = 25.0          # an arc approach's sideways offset from the straight line, at mid-way


class Approach(ChoiceEnum):
    """The shape of a flight's approach (the hover and the descent are the same for both)."""

    STRAIGHT = "straight"
    ARC = "arc"

    @classmethod
    def _label(cls) -> str:
        return "approach"


@dataclass(frozen=True)
class VehicleSample:
    """One vehicle pose at time ``t_s``: local NED position (m), attitude, height above the surface below."""

    t_s: float
    position_ned_m: np.ndarray
    attitude: Attitude
    agl_m: float


def random_view(world: World, rng: np.random.Generator, t_s: float = 0.0) -> VehicleSample:
    """A benchmark view: position in the centre region, random yaw, AGL uniform in 30–90 m, level."""
    n, e = rng.uniform(-VIEW_REGION_HALF_M, VIEW_REGION_HALF_M, 2)
    yaw = rng.uniform(-math.pi, math.pi)
    agl = rng.uniform(*AGL_RANGE_M)
    z = float(world.surface_z(np.array([n]), np.array([e]))[0]) - agl
    return VehicleSample(float(t_s), np.array([n, e, z]), Attitude(0.0, 0.0, float(yaw)), float(agl))


def _smooth(s: np.ndarray) -> np.ndarray:
    return s * s * (3 - 2 * s)


def _clear_spot(world: World, n: float, e: float, radius_m: float = 5.0) -> bool:
    """Open ground: everything within ``radius_m`` is bare terrain (nothing above it)."""
    ang = np.linspace(0, 2 * math.pi, 12, endpoint=False)
    pn = np.concatenate([[n], n + radius_m * np.cos(ang), n + 0.5 * radius_m * np.cos(ang)])
    pe = np.concatenate([[e], e + radius_m * np.sin(ang), e + 0.5 * radius_m * np.sin(ang)])
    return bool(np.all(np.abs(world.surface_z(pn, pe) - world.terrain.z_at(pn, pe)) < 0.05))


def _path_clearance_m(world: World, pts: np.ndarray) -> float:
    """Smallest vertical gap between path points (N×3 NED) and the surfaces below them."""
    return float(np.min(world.surface_z(pts[:, 0], pts[:, 1]) - pts[:, 2]))


def plan_flight(world: World, rng: np.random.Generator, frames: int, fps: float,
                approach: Approach = Approach.STRAIGHT) -> list[VehicleSample]:
    """Approach (40 %), hover (20 %), descent (40 %) towards an open landing spot kept near the image centre.

    With the camera 45° down, the spot sits at the image centre when the horizontal distance to it equals
    the height, so the approach ends and the descent runs along that line of sight. ``approach``: see the
    module docstring (the same random draws for both, so a seed flies to the same spot either way).
    """
    offset_m = ARC_OFFSET_M if approach is Approach.ARC else 0.0
    spots = world.landing_spots
    near = spots[np.all(np.abs(spots) < VIEW_REGION_HALF_M, axis=1)] if len(spots) else spots
    targets = [near[i] for i in rng.permutation(len(near))[:60] if _clear_spot(world, *near[i])][:8]
    n_app = max(1, int(round(frames * 0.4)))
    n_hov = max(0, int(round(frames * 0.2)))
    n_des = max(1, frames - n_app - n_hov)

    def path(target, zt, yaw, n_a, n_d):
        fwd = np.array([math.cos(yaw), math.sin(yaw)])
        s = _smooth(np.linspace(0, 1, n_a))
        dist, height = 170.0 - 110.0 * s, 80.0 - 20.0 * s      # horizontal distance to the spot, height
        app = np.column_stack([target[0] - fwd[0] * dist, target[1] - fwd[1] * dist, zt - height])
        if offset_m:
            side = offset_m * np.sin(math.pi * s)               # to the left of the line, back on it at the end
            app[:, 0] -= fwd[1] * side
            app[:, 1] += fwd[0] * side
        h = 60.0 - 45.0 * _smooth(np.linspace(0, 1, n_d))
        des = np.column_stack([target[0] - fwd[0] * h, target[1] - fwd[1] * h, zt - h])
        return app, des, s

    best = None
    for target in targets or [np.zeros(2)]:
        zt = float(world.terrain.z_at(np.array([target[0]]), np.array([target[1]]))[0])
        for _ in range(12):                             # a heading whose whole path clears what is below
            yaw = rng.uniform(-math.pi, math.pi)
            app, des, _ = path(target, zt, yaw, 60, 60)
            clearance = min(_path_clearance_m(world, app), _path_clearance_m(world, des))
            if best is None or clearance > best[0]:
                best = (clearance, target, zt, yaw)
            if clearance > 12.0:
                break
        assert best is not None   # the first heading tried is always kept
        if best[0] > 12.0:
            break
    assert best is not None       # targets or [np.zeros(2)] is never empty
    _, target, zt, yaw = best
    app, des, s = path(target, zt, yaw, n_app, n_des)
    out: list[VehicleSample] = []
    for k in range(frames):
        t = k / fps
        if k < n_app:
            pos = app[k]
            speed = 4 * s[k] * (1 - s[k]) if n_app > 1 else 0.0
            # Nose down while speeding up; on an arc the camera stays turned towards the spot.
            heading = math.atan2(target[1] - pos[1], target[0] - pos[0]) if offset_m else yaw
            att = Attitude(0.0, float(-0.12 * speed), float(heading))
        elif k < n_app + n_hov:
            w = 2 * math.pi * t
            pos = app[-1] + np.array([0.3 * math.sin(0.7 * w), 0.3 * math.cos(0.5 * w), 0.2 * math.sin(0.3 * w)])
            att = Attitude(0.01 * math.sin(0.9 * w), 0.01 * math.cos(0.6 * w), yaw + 0.01 * math.sin(0.2 * w))
        else:
            pos = des[min(k - n_app - n_hov, len(des) - 1)]
            att = Attitude(0.0, 0.0, float(yaw))
        agl = float(world.surface_z(np.array([pos[0]]), np.array([pos[1]]))[0] - pos[2])
        out.append(VehicleSample(t, np.asarray(pos, np.float64).copy(), att, agl))
    return out


def peak_speed_mps(samples: list[VehicleSample]) -> float:
    """The fastest speed between consecutive samples (0 for fewer than two)."""
    if len(samples) < 2:
        return 0.0
    p = np.array([s.position_ned_m for s in samples])
    t = np.array([s.t_s for s in samples])
    return float(np.max(np.linalg.norm(np.diff(p, axis=0), axis=1) / np.maximum(np.diff(t), 1e-9)))
