"""Sensor noise and rain out of the motion stage's frames: a median of three, aligned on the ground (ARCHITECTURE.md §11).

Each frame the stage measures is replaced by the per-pixel median of itself and the two frames the stage saw
before it (one stage interval apart, 0.2 s by default), both warped onto it by the ground plane's homography
from their telemetry poses. Rain streaks land somewhere else in every frame and sensor noise is independent
from frame to frame: the median drops a streak that covers a pixel in one frame of the three, and cuts the
noise's σ by about 1.5. On rainy and noisy sim flights the flow noise of single frames had kept every pair
from detecting half a metre (MEASUREMENTS, "Three frames, aligned on the ground").

The ground lines up exactly. A point ``h`` above it is displaced between the three by the parallax of 0.2-0.4 s
of motion: under 0.2 px for 1 m at 85 m range and 10 m/s with a 90° lens 640 px across, so small obstacles keep
their place and shape; a tall roof's edge is displaced by pixels and the median places it at about the middle
frame's view. Every frame the stage keeps, keyframes included, is made the same way, so both sides of a pair
are medians over the same stencil and what the pair measures is the parallax between matching middle views,
over the same baseline when the vehicle's velocity is the same at both ends. Frames without a telemetry position (image odometry
places them) are used as they are: their poses are not known well enough to align three frames.

Pure OpenCV/numpy on uint8; memory: the last two frames.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.fusion.parallax import CameraPose, plane_homography


@dataclass(frozen=True)
class BurstConfig:
    """``frames``: 3 (the frame and the two before it) or 1 (off); ``span_s``: earlier frames older than this
    are not used (a gap in the feed, a stage that ran late): the frame is then used as it is."""

    frames: int = 3
    span_s: float = 0.5

    def __post_init__(self) -> None:
        if self.frames not in (1, 3):
            raise InputError(f"motion burst frames must be 1 (off) or 3, got {self.frames}")
        if not self.span_s > 0:
            raise InputError(f"motion burst span_s must be > 0, got {self.span_s}")


@dataclass(frozen=True)
class _Shot:
    time_s: float
    grey: np.ndarray         # as the camera gave it (at the stage's size, undistorted)
    pose: CameraPose


def median3(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Per-pixel median of three same-shaped arrays (uint8 stays uint8)."""
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    out: np.ndarray = np.maximum(lo, np.minimum(hi, c))
    return out


def warp_onto(src: np.ndarray, hom: np.ndarray) -> np.ndarray:
    """``src`` resampled onto the frame whose pixel x maps to ``hom`` @ x in ``src`` (same size)."""
    h, w = src.shape[:2]
    out: np.ndarray = cv2.warpPerspective(src, hom, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                          borderMode=cv2.BORDER_REPLICATE)
    return out


class FrameBurst:
    """The stage's last frames as the camera gave them; :meth:`clean` makes each new one their aligned median."""

    def __init__(self, config: BurstConfig, k_cv: np.ndarray):
        """``k_cv``: the stage's intrinsic matrix, OpenCV's pixel-centre convention."""
        self.config = config
        self.k_cv = k_cv
        self._shots: list[_Shot] = []

    def reset(self) -> None:
        self._shots = []

    def raw_at(self, time_s: float) -> Optional[np.ndarray]:
        """The frame of ``time_s`` as the camera gave it, when it is one of the last two (else None)."""
        for shot in self._shots:
            if shot.time_s == time_s:
                return shot.grey
        return None

    def clean(self, grey: np.ndarray, pose: CameraPose, time_s: float) -> np.ndarray:
        """The median of ``grey`` and the two frames before it warped onto it by the ground plane (``pose``'s
        plane, ``pose.agl_m`` below the camera); ``grey`` itself when either is missing, older than ``span_s``,
        from the future or without a telemetry position, or when this frame has none. Remembers ``grey``."""
        cfg = self.config
        earlier = [s for s in self._shots if 0.0 < time_s - s.time_s <= cfg.span_s]
        self._shots = (earlier + [_Shot(time_s, grey, pose)])[-2:]
        if cfg.frames == 1 or len(earlier) < 2 or not _placed(pose) or not all(_placed(s.pose) for s in earlier):
            return grey
        a, b = (warp_onto(s.grey, plane_homography(self.k_cv, pose, s.pose)[0]) for s in earlier)
        return median3(grey, a, b)


def _placed(pose: CameraPose) -> bool:
    return bool(np.all(np.isfinite(pose.position_ned_m))) and np.isfinite(pose.agl_m) and pose.agl_m > 0
