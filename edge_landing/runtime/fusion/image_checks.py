"""What a frame pair must show before its flow counts as evidence (ARCHITECTURE.md §11).

Motion geometry reads "no parallax" as "level ground". Two inputs give no parallax without being ground:
- **No texture.** Where the image is uniform (a capture card's "no signal" screen, a lens cap, pixels clipped
  at black or white, a digitally smooth region) DIS has nothing to match and fills the flow in from around:
  zero residual parallax, zero flow noise, read as flat and clear. With sensor noise a uniform patch gives
  random flow, which the pair's own noise estimate refuses; without noise nothing does. Not caught: the noise
  passes this check, and next to textured ground DIS fills a smooth patch's flow in from it, so the edge of
  one (murky water, metres wide) still reads level (README, Known limits). A pixel is
  textured when the weakest direction of its local image gradient (the smaller eigenvalue of the structure
  tensor over a small box, as RMS grey levels per pixel) reaches ``min_texture_grey_px``. Ground of any kind
  seen by a real camera, and every rendered ground material of the sim, clears it many times over. A
  textureless pixel may still report an obstacle (a smooth wall's face reads partly high) but cannot confirm,
  like a pixel whose DIS patch is too large (fusion.motion).
- **Images that did not move as the vehicle did.** A frozen feed (the camera or its driver repeating the last
  image) or telemetry that does not belong to the frames: the poses predict that the ground moved by a pixel or
  more, yet the reference image matches the current one better where it was than where the poses put it.

Pure numpy/OpenCV, no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from edge_landing.runtime.core.errors import InputError


@dataclass(frozen=True)
class ImageCheckConfig:
    """Texture and pose-consistency thresholds (grey levels of 8-bit images, pixels)."""

    min_texture_grey_px: float = 0.25   # weakest-direction RMS gradient a pixel needs to carry evidence
    texture_box_px: int = 5             # the box it is measured over (about a DIS patch with its overlap)
    min_textured_share: float = 0.2     # a window with less textured ground gives no evidence at all
    min_predicted_motion_px: float = 1.0   # below this the two errors differ by noise only: not checked
    still_match_ratio: float = 0.5      # unwarped error below this share of the warped one: images did not move

    def __post_init__(self) -> None:
        for name in ("min_texture_grey_px", "min_predicted_motion_px", "still_match_ratio"):
            if not getattr(self, name) > 0:
                raise InputError(f"image check {name} must be > 0, got {getattr(self, name)}")
        if self.texture_box_px < 1:
            raise InputError(f"image check texture_box_px must be >= 1, got {self.texture_box_px}")
        if not 0 <= self.min_textured_share <= 1:
            raise InputError(f"image check min_textured_share must be in [0, 1], got {self.min_textured_share}")


def textured(grey: np.ndarray, config: ImageCheckConfig) -> np.ndarray:
    """H×W bool: pixels whose neighbourhood has texture in every direction (see the module docstring)."""
    f = grey.astype(np.float32)
    gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)     # grey levels per pixel
    gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    box = (config.texture_box_px, config.texture_box_px)
    a = cv2.boxFilter(gx * gx, -1, box)
    b = cv2.boxFilter(gx * gy, -1, box)
    c = cv2.boxFilter(gy * gy, -1, box)
    # Smaller eigenvalue of [[a, b], [b, c]] >= t²  <=>  (a - t²)(c - t²) >= b² with a, c >= t².
    t2 = np.float32(config.min_texture_grey_px ** 2)
    out: np.ndarray = (a >= t2) & (c >= t2) & ((a - t2) * (c - t2) >= b * b)
    return out


def predicted_motion_px(hom: np.ndarray, rows: slice, cols: slice) -> float:
    """Median distance (pixels) that the plane homography ``hom`` (current pixel -> reference pixel) moves the
    window's corners and centre: how far the poses say the ground moved between the two images."""
    u = np.array([cols.start, cols.stop - 1, cols.start, cols.stop - 1, 0.5 * (cols.start + cols.stop - 1)])
    v = np.array([rows.start, rows.start, rows.stop - 1, rows.stop - 1, 0.5 * (rows.start + rows.stop - 1)])
    q = hom @ np.vstack([u, v, np.ones(5)])
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.hypot(q[0] / q[2] - u, q[1] / q[2] - v)
    d = np.where(q[2] > 0, d, np.inf)
    return float(np.median(d))


def moved_as_posed(cur: np.ndarray, ref_same_place: np.ndarray, ref_warped: np.ndarray, motion_px: float,
                   config: ImageCheckConfig) -> bool:
    """False when the poses moved the ground by at least ``min_predicted_motion_px`` but the reference image
    matches the current one better unmoved (``ref_same_place``: the same pixels) than moved by the poses
    (``ref_warped``). All three are the window's grey images (uint8)."""
    if not motion_px >= config.min_predicted_motion_px:
        return True
    still = float(cv2.absdiff(cur, ref_same_place).mean())
    posed = float(cv2.absdiff(cur, ref_warped).mean())
    return not still < config.still_match_ratio * posed
