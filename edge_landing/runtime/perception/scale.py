"""In-flight depth scale from the height above ground (ARCHITECTURE.md §7), pure numpy; runs on the drone.

Pixels the network votes horizontal should lie on the ground plane. A pixel's camera ray r (camera frame,
z = 1 convention) rotated into local NED hits the plane ``agl_m`` below the camera at planar z-depth
``agl_m / (R r)·down``. The frame's scale is the median over those pixels of plane depth / predicted
depth; a running value is kept in log space (exponential smoothing), and a frame that disagrees with it
by more than a gate is not averaged in (a run of disagreeing frames resets it: the terrain changed).

    est = AltitudeScaleEstimator(AltitudeScaleConfig())
    e = est.update(pred.depth_m, pred.hvo_prob, intrinsics, mount, attitude, agl_m=42.0)
    if e.valid:
        metric_depth = pred.depth_m * e.scale
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from edge_landing.runtime.core.camera import (
    Attitude,
    Intrinsics,
    Mount,
    ned_from_camera,
    up_in_camera,
)
from edge_landing.runtime.core.geometry import normals_from_depth, slope_from_normals
from edge_landing.runtime.perception.calibration_file import (
    load_calibration,  # re-exported: both scale sources are found here
)

__all__ = ["AltitudeScaleConfig", "AltitudeScaleEstimator", "FrameScale", "ScaleEstimate", "frame_scale",
           "ground_plane_depth", "load_calibration"]


@dataclass(frozen=True)
class AltitudeScaleConfig:
    """Settings of the in-flight scale estimate.

    ``horizontal_prob``: HVO probability of 'horizontal' a pixel needs to count as ground.
    ``max_slope_rad``: without an HVO head, pixels whose depth-derived normal is within this of up count.
    ``min_depression_rad``: rays closer to the horizon than this are left out (plane depth blows up there).
    ``min_fraction`` / ``min_pixels``: how much ground a frame needs; ``max_spread``: the largest MAD/median
    of the frame's ratios that is still believed. ``alpha``: smoothing weight of a new frame (log space);
    ``gate``: the largest |log(frame / running)| averaged in (10 %: a rangefinder that reads a roof or a tree
    instead of the ground jumps by more than that at these heights); ``reset_after``: consecutive gated
    frames that replace the running value; ``max_hold_frames``: frames a value is kept without a fresh one.
    """

    horizontal_prob: float = 0.5
    max_slope_rad: float = math.radians(10.0)
    min_depression_rad: float = math.radians(5.0)
    min_agl_m: float = 1.0
    min_fraction: float = 0.02
    min_pixels: int = 50
    max_spread: float = 0.25
    alpha: float = 0.3
    gate: float = math.log(1.1)
    reset_after: int = 5
    max_hold_frames: int = 30


@dataclass(frozen=True)
class ScaleEstimate:
    """The running scale after one frame. ``valid`` says whether ``scale`` may be used; ``reason`` says why
    not, or why this frame did not update it. ``frame_scale``/``fraction``/``spread`` describe the frame
    itself (NaN when it had no usable ground); ``quality`` in [0, 1] = fraction × (1 − spread/max_spread)."""

    scale: float
    quality: float
    valid: bool
    reason: str = ""
    frame_scale: float = math.nan
    fraction: float = 0.0
    spread: float = math.nan
    pixels: int = 0


@dataclass(frozen=True)
class FrameScale:
    """One frame's measurement: the median ratio, the share of pixels used, MAD/median, or why none."""

    scale: float
    fraction: float
    spread: float
    pixels: int
    reason: str = ""

    @property
    def ok(self) -> bool:
        return not self.reason


def ground_plane_depth(intrinsics: Intrinsics, mount: Mount, attitude: Attitude, agl_m: float,
                       min_depression_rad: float = 0.0) -> np.ndarray:
    """Planar z-depth (H×W, metres) of flat ground ``agl_m`` below the camera; NaN where the ray does not
    go down by at least ``min_depression_rad``."""
    rays = intrinsics.pixel_rays().astype(np.float64)                  # camera frame, z = 1
    down = rays @ ned_from_camera(mount, attitude)[2]                   # NED z (down) component of each ray
    norm = np.linalg.norm(rays, axis=-1)
    depth = np.full(down.shape, np.nan)
    ok = down > math.sin(min_depression_rad) * norm
    depth[ok] = agl_m / down[ok]
    return depth


def frame_scale(depth_m: np.ndarray, hvo_prob: Optional[np.ndarray], intrinsics: Intrinsics, mount: Mount,
                attitude: Attitude, agl_m: Optional[float],
                config: AltitudeScaleConfig = AltitudeScaleConfig()) -> FrameScale:
    """The scale one frame supports (never raises; a frame without usable ground says why)."""
    def no(reason: str, fraction: float = 0.0, pixels: int = 0) -> FrameScale:
        return FrameScale(math.nan, fraction, math.nan, pixels, reason)

    if agl_m is None or not math.isfinite(agl_m) or agl_m < config.min_agl_m:
        return no(f"no usable height above ground ({agl_m!r}; at least {config.min_agl_m} m needed)")
    depth = np.asarray(depth_m, dtype=np.float64)
    if depth.ndim != 2:
        return no(f"depth has shape {depth.shape}; expected H×W")
    h, w = depth.shape
    if (intrinsics.height, intrinsics.width) != (h, w):
        intrinsics = intrinsics.scaled(w, h)
    if hvo_prob is not None:
        if np.shape(hvo_prob) != (h, w, 3):
            return no(f"HVO probabilities have shape {np.shape(hvo_prob)}; expected {(h, w, 3)}")
        ground = np.asarray(hvo_prob)[..., 0] >= config.horizontal_prob
    else:
        # No HVO head: the direction of a normal does not depend on the depth's scale, so slope still works.
        normals = normals_from_depth(depth.astype(np.float32), intrinsics)
        with np.errstate(invalid="ignore"):
            ground = slope_from_normals(normals, up_in_camera(mount, attitude)) <= config.max_slope_rad
    plane = ground_plane_depth(intrinsics, mount, attitude, agl_m, config.min_depression_rad)
    with np.errstate(invalid="ignore", divide="ignore"):
        use = ground & np.isfinite(plane) & np.isfinite(depth) & (depth > 0)
        pixels = int(use.sum())
        fraction = pixels / float(h * w)
        if pixels < config.min_pixels or fraction < config.min_fraction:
            return no(f"too little ground seen ({pixels} pixels, {fraction:.1%} of the image)", fraction, pixels)
        ratios = plane[use] / depth[use]
    med = float(np.median(ratios))
    spread = float(np.median(np.abs(ratios - med)) / med)
    if spread > config.max_spread:
        return FrameScale(med, fraction, spread, pixels,
                          f"ground ratios disagree (MAD/median {spread:.2f} > {config.max_spread:.2f})")
    return FrameScale(med, fraction, spread, pixels)


class AltitudeScaleEstimator:
    """Running scale from successive frames (see the module docstring)."""

    def __init__(self, config: AltitudeScaleConfig = AltitudeScaleConfig()):
        self.config = config
        self.reset()

    def reset(self) -> None:
        self._log_scale: Optional[float] = None
        self._gated = 0          # consecutive frames that disagreed with the running value
        self._gated_logs: list[float] = []
        self._since_update = 0

    @property
    def scale(self) -> float:
        return math.exp(self._log_scale) if self._log_scale is not None else math.nan

    def update(self, depth_m: np.ndarray, hvo_prob: Optional[np.ndarray], intrinsics: Intrinsics, mount: Mount,
               attitude: Attitude, agl_m: Optional[float]) -> ScaleEstimate:
        cfg = self.config
        fs = frame_scale(depth_m, hvo_prob, intrinsics, mount, attitude, agl_m, cfg)
        quality = 0.0
        if fs.ok:
            quality = float(np.clip(fs.fraction * (1.0 - fs.spread / cfg.max_spread), 0.0, 1.0))
        reason = fs.reason
        if fs.ok:
            new = math.log(fs.scale)
            if self._log_scale is None:
                self._log_scale, self._since_update = new, 0
            elif abs(new - self._log_scale) <= cfg.gate:
                self._log_scale += cfg.alpha * (new - self._log_scale)
                self._gated, self._gated_logs, self._since_update = 0, [], 0
            else:
                self._gated += 1
                self._gated_logs.append(new)
                self._since_update += 1
                reason = (f"frame scale {fs.scale:.4g} disagrees with the running {self.scale:.4g} "
                          f"({self._gated}/{cfg.reset_after} before a reset)")
                if self._gated >= cfg.reset_after:
                    # The disagreeing frames agree among themselves: take their median as the new value.
                    self._log_scale = float(np.median(self._gated_logs))
                    self._gated, self._gated_logs, self._since_update = 0, [], 0
                    reason = f"running scale reset to {self.scale:.4g} after {cfg.reset_after} disagreeing frames"
        else:
            self._since_update += 1
        if self._log_scale is None:
            return ScaleEstimate(math.nan, quality, False, reason or "no scale yet", fs.scale, fs.fraction,
                                 fs.spread, fs.pixels)
        if self._since_update > cfg.max_hold_frames:
            return ScaleEstimate(self.scale, quality, False,
                                 f"scale is stale: no agreeing frame for {self._since_update} frames"
                                 + (f" ({reason})" if reason else ""), fs.scale, fs.fraction, fs.spread, fs.pixels)
        return ScaleEstimate(self.scale, quality, True, reason, fs.scale, fs.fraction, fs.spread, fs.pixels)
