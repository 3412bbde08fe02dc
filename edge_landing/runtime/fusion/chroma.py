"""Colour for the residual check: people whose grey matches the ground behind them (ARCHITECTURE.md §11).

Motion geometry measures on grey. A person in red on green grass of the same grey, or in dark blue on dark grass,
is matched by the ground's flow and leaves no grey residual (fusion.residual). Their colour still differs: the
chroma residual (YCrCb's Cr and Cb, after the same flow) passed 4 × the window's median next to 80-85 % of such
people from 50 m, where grey passed next to 27 % (docs/MEASUREMENTS.md, "People: what the flow leaves
unmatched"). Cameras carry chroma at half resolution, and so does the keyframe ring here: ``ChromaMaker`` turns a
frame into its half-size Cr, Cb (undistorted like the grey), and ``chroma_unmatched`` warps a keyframe's onto
the current window through the plane homography and the grey flow, then judges each channel as the grey one.
Pure numpy/OpenCV, no I/O.
"""
from __future__ import annotations

from typing import Optional, Sequence

import cv2
import numpy as np

from edge_landing.runtime.fusion.keyframes import warp_window
from edge_landing.runtime.fusion.residual import ResidualConfig, unmatched_pixels

# Full-size pixel (x, y) -> half-size pixel ((x + 0.5) / 2 - 0.5, ...): OpenCV's centres at integers.
_TO_HALF = np.array([[0.5, 0.0, -0.25], [0.0, 0.5, -0.25], [0.0, 0.0, 1.0]])


class ChromaMaker:
    """RGB frames -> Cr, Cb at half the stage's size (H/2 × W/2 × 2 uint8), undistorted when the lens is."""

    def __init__(self, k_cv: np.ndarray, dist: Optional[Sequence[float]], size_hw: tuple[int, int]):
        h, w = size_hw
        self.half_hw = (max(1, h // 2), max(1, w // 2))
        self._undistort = None
        if dist:
            k_half = _TO_HALF @ k_cv
            self._undistort = cv2.initUndistortRectifyMap(k_half, np.asarray(dist, np.float64), None, k_half,
                                                          (self.half_hw[1], self.half_hw[0]), cv2.CV_16SC2)

    def __call__(self, image: np.ndarray) -> Optional[np.ndarray]:
        """None for a grey image (no colour to compare)."""
        if image.ndim != 3 or image.shape[2] != 3:
            return None
        h2, w2 = self.half_hw
        small = cv2.resize(image, (w2, h2), interpolation=cv2.INTER_LINEAR)   # 2 × 2 means at exactly half size
        if small.dtype != np.uint8:
            small = np.clip(small, 0, 255).astype(np.uint8)
        if self._undistort is not None:
            small = cv2.remap(small, self._undistort[0], self._undistort[1], cv2.INTER_LINEAR)
        return np.ascontiguousarray(cv2.cvtColor(small, cv2.COLOR_RGB2YCrCb)[..., 1:])


def chroma_unmatched(cur_half: np.ndarray, ref_half: np.ndarray, hom: np.ndarray, window: tuple[slice, slice],
                     to_ref: tuple[np.ndarray, np.ndarray], usable: np.ndarray, inside: np.ndarray,
                     config: ResidualConfig, rain_share: float = 0.0, flow_noise_px: float = 0.0) -> np.ndarray:
    """Pixels of the current ``window`` whose chroma the flow-warped keyframe's does not match (H×W bool).

    ``cur_half``, ``ref_half``: half-size Cr, Cb of the current frame and the keyframe; ``hom``: the plane
    homography (current frame pixel -> keyframe pixel, full size); ``to_ref``: the grey flow's remap maps (x, y of
    each window pixel's match in the plane-warped window, as the grey residual uses them); ``usable``, ``inside``:
    ``rain_share``, ``flow_noise_px``: as for residual.unmatched_pixels.
    """
    if not config.checks(rain_share, flow_noise_px):            # (before the warps: nothing to judge)
        return np.zeros(usable.shape, bool)
    cur = warp_window(cur_half, _TO_HALF, window)               # both at the window's full-size pixels
    ref = warp_window(ref_half, _TO_HALF @ hom, window)
    matched = cv2.remap(ref, to_ref[0], to_ref[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    out = np.zeros(cur.shape[:2], bool)
    for ch in range(2):
        out |= unmatched_pixels(np.ascontiguousarray(cur[..., ch]), np.ascontiguousarray(matched[..., ch]), usable,
                                inside, config, rain_share, config.chroma_floor, flow_noise_px)
    return out
