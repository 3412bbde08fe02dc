"""Motion-geometry settings and the per-pair result (ARCHITECTURE.md §11); the stage is in fusion.motion.

Frames: camera = OpenCV (x right, y down, z forward), world = local NED. Pure data, no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from edge_landing.runtime.core.choices import ChoiceEnum
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.fusion.burst import BurstConfig
from edge_landing.runtime.fusion.image_checks import ImageCheckConfig
from edge_landing.runtime.fusion.image_motion import ImagePoseConfig
from edge_landing.runtime.fusion.plane_sweep import SweepConfig
from edge_landing.runtime.fusion.residual import ResidualConfig
from edge_landing.runtime.fusion.rotation_fit import RotationFitConfig
from edge_landing.runtime.fusion.streaks import StreakConfig

POSE_TELEMETRY, POSE_IMAGE = "telemetry", "image"


class DisPreset(ChoiceEnum):
    ULTRAFAST = "ultrafast"
    FAST = "fast"
    MEDIUM = "medium"

    @classmethod
    def _label(cls) -> str:
        return "DIS optical flow preset"

    def create(self) -> cv2.DISOpticalFlow:
        preset = {DisPreset.ULTRAFAST: cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
                  DisPreset.FAST: cv2.DISOPTICAL_FLOW_PRESET_FAST,
                  DisPreset.MEDIUM: cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}[self]
        return cv2.DISOpticalFlow.create(preset)


@dataclass(frozen=True)
class MotionConfig:
    """Motion-geometry settings. Pixels at the frame's own size (up to ``max_width_px``), metres, seconds."""

    # DIS runs on at most this many pixels per frame (height, width): the ground band of the frame at its own
    # resolution, cropped around the candidate spot when the band is larger. Full resolution matters: the
    # parallax of a 1 m obstacle at 40-60 m height is a fraction of a pixel at 160 px across (docs §11).
    window_hw: tuple[int, int] = (120, 160)
    max_width_px: int = 1280             # wider frames are downscaled first (bounds the keyframe memory)
    history_s: float = 8.0               # keyframes older than this are dropped ...
    max_frames: int = 16                 # ... and at most this many are kept (thinned to history_s / max_frames)
    flow_noise_px: float = 0.2           # floor of the residual flow's 1-σ error (each pair measures its own)
    detect_sigmas: float = 3.0           # a height is detectable at this many σ
    enough_detect_m: float = 0.25        # the newest keyframe detecting this is preferred to longer baselines
    max_baseline_ratio: float = 0.5     # keyframes farther than this × the range to the ground are not paired
    focus_preference: float = 1.5        # the first candidate spot's window wins unless another detects this × less
    dis_preset: DisPreset = DisPreset.FAST
    dis_patch_px: int = 4                # DIS patch side and stride: the patch's footprint on the ground
    dis_patch_stride_px: int = 2         # bounds the narrowest feature resolved (max_patch_footprint_m)
    dis_refine_iterations: int = 5       # variational refinement (the fast preset's 1 leaves a ~0.1 px bias)
    dis_finest_scale: int = 0            # pyramid level DIS stops at (1 = half size: sub-pixel parallax of
                                         # small obstacles survives; 2 halves a car-sized parallax)
    max_range_m: float = 80.0            # ground farther than this (horizontally) from the vehicle is skipped
    # DIS smooths over its patch: a gap or an obstacle narrower than the patch's footprint on the ground
    # (patch px × range / f) reads at a fraction of its height (1.6 m gaps between packed cars vanished at
    # 1.9 m footprint). Pixels with a larger footprint still report obstacles but cannot confirm.
    max_patch_footprint_m: float = 1.5
    # An obstacle narrower than that footprint reads at about 1.2 × its width / footprint of its height (a 0.25 m
    # garden wall at 0.93 m: a third). A cell confirms only what an obstacle thin_obstacle_m / 1.2 across (2/3 m:
    # a crate, a small bush) would have shown: its detectable height counts footprint / thin_obstacle_m times,
    # at least once (its pixels' largest). Thinner walls and posts are seen only where the footprint is small
    # enough. 0: off.
    thin_obstacle_m: float = 0.8
    min_overlap: float = 0.5             # share of probe points the reference frame must see
    max_photometric_error: float = 24.0  # grey levels: larger residual after flow = no evidence (occlusion)
    max_cross_parallax_px: float = 1.5   # residual across the epipolar direction beyond this = no evidence
    max_sigma_h_m: float = 1.0           # pixels noisier than this are left out of the terrain fit
    min_agl_m: float = 2.0               # below this the plane model is not used
    max_plane_noise_px: float = 0.6      # a pair noisier than this does not update the ground plane's level
    # An oblique view sees ground under tree crowns and eaves: a pixel confirms only where the air above its
    # ground point, up to this height, was seen empty in the same window (parallax.column_seen; 0: off).
    overhang_check_m: float = 8.0
    image_pose: ImagePoseConfig = ImagePoseConfig()   # the fallback when telemetry has no position
    streaks: StreakConfig = StreakConfig()            # rain streaks filled in before the flow (fusion.streaks)
    burst: BurstConfig = BurstConfig()                # each frame the median of three aligned ones (fusion.burst)
    sweep: SweepConfig = SweepConfig()                # the plane a window is measured against (fusion.plane_sweep)
    checks: ImageCheckConfig = ImageCheckConfig()     # texture and moving-as-posed (fusion.image_checks)
    rotation_fit: RotationFitConfig = RotationFitConfig()   # the telemetry's rotation drift (fusion.rotation_fit)
    residual: ResidualConfig = ResidualConfig()       # what the flow left unmatched (fusion.residual)

    def __post_init__(self) -> None:
        h, w = self.window_hw
        if h < 32 or w < 32 or self.max_width_px < 32:
            raise InputError(f"motion window must be at least 32x32 pixels, got {h}x{w} (max width "
                             f"{self.max_width_px})")
        for name in ("history_s", "flow_noise_px", "detect_sigmas", "max_range_m", "max_photometric_error",
                     "max_cross_parallax_px", "max_sigma_h_m", "min_agl_m", "enough_detect_m",
                     "max_patch_footprint_m", "max_plane_noise_px", "max_baseline_ratio",
                     "focus_preference"):
            if not getattr(self, name) > 0:
                raise InputError(f"motion {name} must be > 0, got {getattr(self, name)}")
        for name in ("overhang_check_m", "thin_obstacle_m"):
            if not getattr(self, name) >= 0:
                raise InputError(f"motion {name} must be >= 0, got {getattr(self, name)}")
        if self.max_frames < 2:
            raise InputError(f"motion max_frames must be at least 2, got {self.max_frames}")
        if not 0 < self.min_overlap <= 1:
            raise InputError(f"motion min_overlap must be in (0, 1], got {self.min_overlap}")


@dataclass(frozen=True)
class ParallaxResult:
    """Per-pixel evidence of one frame pair on the window ``rows`` × ``cols`` of the frame at the stage's size.

    ``height_m``: height above the local ground (NaN where there is no evidence); ``detectable_m``: the
    smallest height this pair could have detected at that pixel (inf where no evidence); ``ned_m``: the
    pixel's point in local NED (3×H×W, at its measured height). ``baseline_m``: distance between the two
    camera centres; ``reference_age_s``: how old the reference frame was.
    """

    time_s: float
    rows: slice
    cols: slice
    height_m: np.ndarray
    sigma_m: np.ndarray
    detectable_m: np.ndarray
    ned_m: np.ndarray
    baseline_m: float
    reference_age_s: float
    ground_fit: np.ndarray           # quadratic terrain coefficients (1, n, e, n², ne, e²), n/e in 100 m
    flow_noise_px: float = float("nan")  # the flow noise used: measured across the epipolar lines, floored
    # Pixels the reference frame saw but the plane-plus-parallax model could not explain (photometric or
    # across-epipolar mismatch: occlusion by something tall, a parallax beyond the flow's reach). Pixels
    # outside the reference frame or beyond max_range_m are neither measured nor unexplained: no evidence.
    unexplained: Optional[np.ndarray] = None
    pose_source: str = POSE_TELEMETRY    # where the baseline came from: telemetry positions or the images
    pose_sigma_m: float = 0.0            # 1-σ error of the image pose's worst direction (0: telemetry)
    rain_share: float = 0.0              # share of the window found to be rain, when filled in (fusion.streaks)
    plane_raised_m: float = 0.0          # the plane's height above the ground's level (a roof; fusion.plane_sweep)
    # North, east (N×2, local NED) where something the flow did not match may stand: the rays of pixels too
    # thin for the flow, from the ground up to a person's height (fusion.residual). Obstacle evidence only.
    unmatched_ne_m: Optional[np.ndarray] = None
    # Per pixel, how many times its detectable height a thin obstacle (MotionConfig.thin_obstacle_m wide) must
    # stand to read as high (the patch's footprint over that width, at least 1). What confirmation goes by.
    thin_factor: Optional[np.ndarray] = None
