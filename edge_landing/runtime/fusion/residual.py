"""What the flow left unmatched: small things that stand out of the ground too thin for DIS (ARCHITECTURE.md §11).

DIS smooths its flow over its patch and across a variational neighbourhood. An object a few pixels wide (a
standing person from 50 m is 2 × 5 pixels at 640×480) is filled in with the ground's flow around it, so its
height reads at a fraction of the truth (a 1.7 m person at 0-0.3 m) and the cell it stands in confirmed clear.
The flow did not *match* it, though: after warping the reference by the flow, the current image still differs
there (the person's head is where the reference shows grass, and the grass it hides in one view shows in the
other). On open ground the matched images agree to the sensor's noise.

Flow errors leave a residual where the image has texture (interpolation, DIS's sub-pixel error times the local
gradient), and sensor noise everywhere. So the residual is judged against both: a pixel is *unmatched* where the
mean of ``|current - matched reference|`` over a ``box_px`` box, divided by ``floor_grey`` plus the mean
gradient magnitude there (about "how many pixels off the flow is"), exceeds ``ratio`` × the window's median of
the same (at least ``min_median``: on ground of one colour the chroma's median is the rounding's). The
reference's gain and offset are fitted to the current image first (white balance and exposure differ between
frames). Rain streaks are new in every frame and unmatched too: a pair whose rain filter found
rain (fusion.streaks) is not checked. Nor is a pair whose flow failed (its noise above ``max_flow_noise_px``,
the level above which a pair may not move the ground plane either): where the flow is pixels off, a third of
the window is "unmatched", and on a noisy sensor's flight those pairs' votes kept open ground marked as
obstacles long after good pairs had measured it clear. Unmatched pixels are obstacle evidence that votes in
the grid (fusion.motion_grid): a person is unmatched in most pairs that see them, open ground in few. Never
evidence of clear ground.

What is too wide to be thin: an unmatched region that holds an ellipse ``max_region_m`` across on the ground
is not something the flow smoothed over (DIS measures anything wider than its patch, 0.5-0.8 m of ground) but
ground the reference did not show as it is: on urban flights a building between an approach keyframe and the
plaza hid thousands of pixels of open ground from it while the rest of the window matched to 0.2-0.4 px, and
14 such pairs marked 13-71 % of the open ground in their windows. Those regions (a morphological opening, grown by
``region_margin_px`` to take their ragged rims) do not vote; their pixels remain unexplained for the pair's
heights all the same.

Where it stands: an unmatched pixel's ground point (where its ray meets the ground) lies *behind* what it shows
when that is above the ground: a person's head seen 45° down is 1.7 m beyond their feet. So the evidence is
placed on every cell its ray crosses from the ground up to ``reach_m`` (``ray_footprints``); marked at the
ground point alone, a person's own cells stayed clear. Pure numpy/OpenCV, no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.fusion.parallax import CameraPose, ned_points


@dataclass(frozen=True)
class ResidualConfig:
    """Grey levels of 8-bit images, pixels; ``ratio`` 0 turns the check off."""

    ratio: float = 4.0          # × the window's median (gradient-relative) residual: above it, unmatched
    floor_grey: float = 8.0     # grey levels added to the gradient: residual of noise where there is no texture
    colour: bool = True         # check Cr and Cb too (fusion.chroma): people whose grey matches the ground
    chroma_floor: float = 2.0   # the same floor for the chroma channels (levels of 8-bit Cr, Cb)
    max_rain_share: float = 0.01   # a pair with more of its window found to be rain is not checked
    max_flow_noise_px: float = 0.6  # nor a pair whose flow noise is above this (the flow failed there)
    box_px: int = 3             # the residual is averaged over this box (a person's width at 50 m)
    min_pixels: int = 100       # fewer matched pixels than this: no scale, nothing is unmatched
    # The window's median is taken as at least this: on ground of one colour (asphalt, concrete) the chroma
    # residual's median is ~0.01, and 4 × that took quantisation for a mismatch on a fifth of the window.
    min_median: float = 0.15
    reach_m: float = 2.0        # metres above the ground an unmatched pixel may show (a standing person)
    reach_steps: int = 9        # points along its ray up to there (0.25 m apart in height)
    max_region_m: float = 3.0   # unmatched regions holding an ellipse this wide on the ground do not vote (0: all do)
    region_margin_px: int = 2   # ... nor the pixels within this many of them (their ragged rims)

    def checks(self, rain_share: float, flow_noise_px: float = 0.0) -> bool:
        """Whether a pair whose rain filter found ``rain_share`` of its window to be rain, and whose flow's noise
        is ``flow_noise_px``, is checked at all (NaN noise: not checked)."""
        return self.ratio > 0 and rain_share <= self.max_rain_share and flow_noise_px <= self.max_flow_noise_px

    def __post_init__(self) -> None:
        if not self.ratio >= 0 or not self.reach_m >= 0 or not self.max_rain_share >= 0 or not self.min_median >= 0:
            raise InputError(f"residual ratio, reach_m, max_rain_share and min_median must be >= 0, got {self.ratio}, "
                             f"{self.reach_m}, {self.max_rain_share}, {self.min_median}")
        if not self.max_region_m >= 0 or self.region_margin_px < 0:
            raise InputError(f"residual max_region_m and region_margin_px must be >= 0, got {self.max_region_m}, "
                             f"{self.region_margin_px}")
        if not self.max_flow_noise_px > 0:
            raise InputError(f"residual max_flow_noise_px must be > 0, got {self.max_flow_noise_px}")
        if not self.floor_grey > 0 or not self.chroma_floor > 0:
            raise InputError(f"residual floor_grey and chroma_floor must be > 0, got {self.floor_grey}, "
                             f"{self.chroma_floor}")
        if self.box_px < 1 or self.min_pixels < 1 or self.reach_steps < 1:
            raise InputError(f"residual box_px, min_pixels and reach_steps must be >= 1, got {self.box_px}, "
                             f"{self.min_pixels}, {self.reach_steps}")


def unmatched_pixels(cur: np.ndarray, matched: np.ndarray, usable: np.ndarray, inside: np.ndarray,
                     config: ResidualConfig, rain_share: float = 0.0, floor_grey: Optional[float] = None,
                     flow_noise_px: float = 0.0) -> np.ndarray:
    """Pixels of ``cur`` the flow-warped reference ``matched`` (same shape, one channel) does not match (H×W bool).

    ``usable``: pixels whose residual sets the scale and the gain (matched, textured); ``inside``: pixels the
    reference saw (elsewhere the residual is no evidence and nothing is unmatched); ``rain_share``: the share of
    the window the rain filter found to be rain; ``floor_grey``: the noise floor (default ``config.floor_grey``);
    ``flow_noise_px``: the pair's flow noise (``ResidualConfig.checks``).
    """
    out = np.zeros(cur.shape, bool)
    usable = usable & inside
    if not config.checks(rain_share, flow_noise_px) or int(usable.sum()) < config.min_pixels:
        return out
    c, m = cur.astype(np.float32), matched.astype(np.float32)
    # The gain and the median from every other pixel each way: a quarter of the work, and the statistics of tens
    # of thousands of pixels do not need them all.
    sample = np.zeros_like(usable)
    sample[::2, ::2] = usable[::2, ::2]
    if int(sample.sum()) < config.min_pixels:
        sample = usable
    x, y = m[sample], c[sample]
    var = float(np.var(x))
    gain = float(np.clip(np.cov(x, y, bias=True)[0, 1] / var, 0.5, 2.0)) if var > 1e-6 else 1.0
    offset = float(np.mean(y) - gain * np.mean(x))
    box = (config.box_px, config.box_px)
    diff = np.where(inside, np.abs(c - (gain * m + offset)), 0.0).astype(np.float32)
    grad = np.asarray(cv2.magnitude(cv2.Sobel(c, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(c, cv2.CV_32F, 0, 1, ksize=3)),
                      np.float32) / np.float32(8.0)      # grey levels per pixel (the 3×3 Sobel's weights sum to 8)
    floor = config.floor_grey if floor_grey is None else floor_grey
    rel = cv2.boxFilter(diff, -1, box, borderType=cv2.BORDER_REFLECT) / (
        floor + cv2.boxFilter(grad, -1, box, borderType=cv2.BORDER_REFLECT))
    out[...] = inside & (rel > config.ratio * max(float(np.median(rel[sample])), config.min_median))
    return out


def without_wide_regions(odd: np.ndarray, pose: CameraPose, k: np.ndarray, corner_px: tuple[int, int],
                         config: ResidualConfig) -> np.ndarray:
    """``odd`` (H×W bool, a window whose top-left pixel is ``corner_px`` = (column, row) in an image with camera
    matrix ``k``) without its regions that hold an ellipse ``config.max_region_m`` across on the ground plane
    ``pose.agl_m`` below, nor the pixels within ``config.region_margin_px`` of them. The ellipse is the window
    centre's: ``max_region_m`` over the ground's metres per pixel across the image, and over its foreshortened
    metres per pixel down the image."""
    if config.max_region_m <= 0 or not odd.any():
        return odd
    h, w = odd.shape
    ray = np.linalg.solve(k, np.array([corner_px[0] + 0.5 * (w - 1), corner_px[1] + 0.5 * (h - 1), 1.0]))
    ray /= np.linalg.norm(ray)
    cos_in = float((pose.r_nc @ ray)[2])           # the ray's cosine to straight down: its incidence on the ground
    if not cos_in > 0.05 or not pose.agl_m > 0:
        return odd
    per_px = pose.agl_m / cos_in / (0.5 * (k[0, 0] + k[1, 1]))     # ground metres per pixel across the ray
    size = (max(3, int(round(config.max_region_m / per_px)) | 1),
            max(3, int(round(config.max_region_m * cos_in / per_px)) | 1))
    mask = odd.astype(np.uint8)
    wide = cv2.morphologyEx(mask, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, size))
    if not wide.any():
        return odd
    if config.region_margin_px > 0:
        side = 2 * config.region_margin_px + 1
        wide = cv2.dilate(wide, np.ones((side, side), np.uint8))
    kept: np.ndarray = odd & (wide == 0)
    return kept


def ray_footprints(pose: CameraPose, xc: np.ndarray, ground_m: np.ndarray, config: ResidualConfig) -> np.ndarray:
    """North, east (N×2, local NED) of the points where the rays of normalised pixels ``xc`` (2×K, camera frame)
    cross heights 0 to ``reach_m`` above their local ground, which lies ``ground_m`` (K) above the plane
    ``pose.agl_m`` below the camera: every place something standing there up to that tall can be."""
    heights = np.linspace(0.0, config.reach_m, config.reach_steps)
    above_plane = np.asarray(ground_m, np.float64)[None, :] + heights[:, None]          # S×K
    lam_scale = np.clip(1.0 - above_plane / pose.agl_m, 0.05, 20.0)
    rays = np.broadcast_to(np.asarray(xc, np.float64)[:, None, :], (2,) + lam_scale.shape)
    pts, nx = ned_points(pose, rays, lam_scale)
    ok = (nx > 0) & np.isfinite(pts[0]) & np.isfinite(pts[1])
    return np.stack([pts[0][ok], pts[1][ok]], axis=1).astype(np.float32)
