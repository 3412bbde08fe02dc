"""Analytic scenes for the fusion tests: exact ray casting against planes and axis-aligned boxes.

World = local NED (ground at down = 0, the vehicle above it at negative down). Depth is planar z-depth:
with camera rays K⁻¹[u, v, 1] (z = 1), the ray parameter at the hit is the z-depth itself.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from edge_landing.runtime.core.camera import (
    Attitude,
    Intrinsics,
    Mount,
    ned_from_camera,
)
from edge_landing.runtime.core.geometry import HvoThresholds
from edge_landing.runtime.core.messages import Prediction, VehicleState


@dataclass(frozen=True)
class Plane:
    """Points x with normal·x = offset (normal is normalised)."""

    normal: tuple
    offset: float


@dataclass(frozen=True)
class Box:
    lo: tuple   # (north, east, down) minimum corner
    hi: tuple


@dataclass
class Render:
    depth_m: np.ndarray        # H×W planar depth, NaN = no hit
    labels: np.ndarray         # H×W uint8 HVO (0/1/2, 255 = no hit)
    points_ned: np.ndarray     # H×W×3 world points (NaN = no hit)
    fx_px: float = 80.0        # focal length of the render (for the working-pixel footprint)

    def probs(self) -> np.ndarray:
        """One-hot H×W×3 probabilities from the labels (zeros where there is no hit)."""
        out = np.zeros(self.labels.shape + (3,), dtype=np.float32)
        for k in range(3):
            out[..., k] = self.labels == k
        return out


@dataclass(frozen=True)
class Scene:
    planes: tuple = (Plane((0.0, 0.0, 1.0), 0.0),)    # ground: down = 0
    boxes: tuple = ()
    thresholds: HvoThresholds = field(default_factory=HvoThresholds)

    def render(self, intr: Intrinsics, mount: Mount, attitude: Attitude, position_ned) -> Render:
        o = np.asarray(position_ned, dtype=np.float64)
        d = intr.pixel_rays().astype(np.float64) @ ned_from_camera(mount, attitude).T
        t_best = np.full(d.shape[:2], np.inf)
        n_best = np.full(d.shape, np.nan)
        for pl in self.planes:
            n = np.asarray(pl.normal, dtype=np.float64)
            n = n / np.linalg.norm(n)
            den = d @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (pl.offset - n @ o) / den
            hit = (t > 0) & (t < t_best)
            t_best[hit] = t[hit]
            n_best[hit] = n
        for box in self.boxes:
            lo, hi = np.asarray(box.lo, float), np.asarray(box.hi, float)
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (lo - o) / d
                t2 = (hi - o) / d
            tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
            t_near = np.nanmax(tmin, axis=-1)
            axis = np.nanargmax(tmin, axis=-1)
            t_far = np.nanmin(tmax, axis=-1)
            hit = (t_near <= t_far) & (t_near > 0) & (t_near < t_best)
            t_best[hit] = t_near[hit]
            nrm = np.zeros(d.shape)
            np.put_along_axis(nrm, axis[..., None], -np.sign(np.take_along_axis(d, axis[..., None], -1)), -1)
            n_best[hit] = nrm[hit]
        ok = np.isfinite(t_best)
        depth = np.where(ok, t_best, np.nan).astype(np.float32)
        pts = np.where(ok[..., None], o + d * np.where(ok, t_best, np.nan)[..., None], np.nan)
        theta = np.arccos(np.clip(np.abs(n_best[..., 2]), 0.0, 1.0))   # angle between normal and up
        labels = np.full(depth.shape, 255, dtype=np.uint8)
        labels[ok & (theta <= self.thresholds.horizontal_max_rad)] = 0
        labels[ok & (theta >= self.thresholds.vertical_min_rad)] = 1
        labels[ok & (theta > self.thresholds.horizontal_max_rad) & (theta < self.thresholds.vertical_min_rad)] = 2
        return Render(depth, labels, pts, intr.fx)


def tilted_plane(slope_rad: float, through=(0.0, 0.0, 0.0)) -> Plane:
    """A plane rising towards north at ``slope_rad``, through a NED point."""
    n = np.array([math.sin(slope_rad), 0.0, math.cos(slope_rad)])
    return Plane(tuple(n), float(n @ np.asarray(through, float)))


def prediction(render: Render, frame_id: int = 0, t_s: float = 0.0, hvo: bool = True) -> Prediction:
    return Prediction(frame_id, t_s, render.depth_m, render.probs() if hvo else None)


def state_at(t_s: float, position_ned, attitude: Attitude = Attitude(), with_position: bool = True) -> VehicleState:
    return VehicleState(t_s, attitude, np.asarray(position_ned, float) if with_position else None)


def target_ned(target, position, attitude: Attitude = Attitude()) -> np.ndarray:
    """World position of a target from its body FRD vector (independent of the target's NED output)."""
    return np.asarray(position, float) + attitude.ned_from_body() @ target.position_body_frd_m


def check_target_on_gt(target, render: Render, where: str, config=None) -> None:
    """The requested clearance strictly; the reported clearance less one working pixel's footprint.

    Fusion sees the scene at the working size: a thing narrower than one working pixel (a roof unit seen
    at 80 m) can be missed, so beyond the requested disc only what a working pixel resolves is promised.
    'Same height' allows the rise of ground that still counts as horizontal (slope <= max_slope_rad).
    """
    from edge_landing.runtime.fusion.fuser import FusionConfig

    cfg = config or FusionConfig()
    need = cfg.required_clearance_m
    hfov = 2.0 * math.atan(render.depth_m.shape[1] / (2.0 * render.fx_px))
    pixel_m = target.range_m * hfov / cfg.working_hw[1]
    for radius in (need, max(need, target.clearance_m - pixel_m)):
        tol = radius * math.tan(cfg.max_slope_rad) + 0.05
        ok, n, why = gt_disc_ok(render, target.position_ned_m, radius, tol)
        assert ok, f"{where}: {why} within {radius:.2f} m ({n} GT points)"


def gt_disc_ok(render: Render, centre_ned, radius_m: float, height_tol_m: float = 0.2) -> tuple:
    """Are all GT points within ``radius_m`` (horizontal) of the centre horizontal and at its height?

    Returns (ok, number of GT points in the disc, what failed).
    """
    p = render.points_ned
    ok_px = np.isfinite(p[..., 0])
    dist = np.hypot(p[..., 0] - centre_ned[0], p[..., 1] - centre_ned[1])
    inside = ok_px & (dist <= radius_m)
    n = int(inside.sum())
    if n == 0:
        return True, 0, ""
    not_h = int(np.count_nonzero(render.labels[inside] != 0))
    dh = float(np.max(np.abs(p[..., 2][inside] - centre_ned[2])))
    if not_h:
        return False, n, f"{not_h} non-horizontal GT points in the disc"
    if dh > height_tol_m:
        return False, n, f"height differs by {dh:.2f} m in the disc"
    return True, n, ""
