"""Plane sweep: the level of the surface a motion window looks at, from the two images alone (ARCHITECTURE.md §11).

The motion stage warps the keyframe by a horizontal plane's homography so that DIS only has to find the residual
parallax. The ground's level (rangefinder, or the ground last measured) is right for a street; a window on a roof
15 m above it leaves the roof with tens of pixels of parallax, more than the flow follows, so the pair fails (flow
noise of 10-25 px) and a spot on the roof is never measured. Here horizontal planes from the ground up towards
the camera are tried on a quarter-size copy of the window: the keyframe is warped by each plane's homography and
compared with the current window by zero-mean normalised cross-correlation. A higher plane is used only when it
explains the window clearly better than the ground's.

A level only chooses the plane heights are measured against (they are still the parallax against the local fit
of the measured surface, fusion.motion), so a wrong one only makes the flow fail. On a raised plane a pixel
may confirm only where its own neighbourhood matches that plane (``SweepResult.verified``): DIS smooths a
roof's flow over a narrow deep gap between two roofs, which then reads as roof. No network output is used. Frames as
fusion.parallax: camera = OpenCV, world = local NED; levels are the plane's distance below the camera (m).
Pure numpy/OpenCV, no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.fusion.parallax import CameraPose, plane_homography

__all__ = ["SweepConfig", "SweepResult", "sweep_plane"]


@dataclass(frozen=True)
class SweepConfig:
    """Plane-sweep settings (pixels at the motion stage's frame size)."""

    enabled: bool = False         # opt-in: measured on 42 sim flights, it confirmed no roof (docs/MEASUREMENTS.md, "Roofs")
    scale: float = 0.25           # the window is compared at this share of its size
    step_px: float = 4.0          # adjacent levels move the window's centre this far in the keyframe (at most)
    max_levels: int = 16          # ... unless that needs more levels: then they are spread evenly
    top_share: float = 0.8        # levels from the ground up to this share of the way to the camera
    min_gain: float = 0.15        # a higher level is used when its correlation beats the ground's by this much
    min_raise_m: float = 3.0      # ... and it is at least this far above the ground (a roof, not cars or clutter)
    min_overlap: float = 0.6      # share of the window the warped keyframe must cover for a level to count
    # On a raised plane a pixel may confirm only where its own 3×3 neighbourhood (at the sweep's scale) matches
    # that plane (±1 level) clearly better than any level farther away: its mean |difference| at most
    # ``verify_ratio`` × the best far level's and ``verify_margin`` grey levels below it. DIS smooths the roof's
    # flow over a narrow deep gap (an alley between two roofs), which then reads as roof.
    verify_ratio: float = 0.75
    verify_margin: float = 1.0

    def __post_init__(self) -> None:
        if not 0.05 <= self.scale <= 1.0:
            raise InputError(f"plane sweep scale must be in [0.05, 1], got {self.scale}")
        if not self.step_px > 0 or self.max_levels < 2:
            raise InputError(f"plane sweep needs step_px > 0 and max_levels >= 2, got {self.step_px}, "
                             f"{self.max_levels}")
        if not 0.0 < self.top_share < 1.0 or not 0.0 < self.min_overlap <= 1.0 or not self.min_gain >= 0 \
                or not self.min_raise_m >= 0 or not self.verify_ratio > 0:
            raise InputError(f"plane sweep top_share must be in (0, 1), min_overlap in (0, 1], min_gain >= 0, "
                             f"min_raise_m >= 0 and verify_ratio > 0, got {self.top_share}, {self.min_overlap}, "
                             f"{self.min_gain}, {self.min_raise_m}, {self.verify_ratio}")


@dataclass(frozen=True)
class SweepResult:
    """The level the window is measured against, the ground's level, and their correlations (NaN: not scored).

    ``verified``: on a raised plane, the window's pixels (full size) whose own neighbourhood matches that
    plane (None on the ground's plane, where nothing changes)."""

    level_m: float
    ground_m: float
    score: float
    ground_score: float
    verified: Optional[np.ndarray] = None

    @property
    def raised(self) -> bool:
        return self.level_m != self.ground_m


class _Homographies:
    """Pixel homographies current -> keyframe of the horizontal planes at 1/d, optionally between rescaled pixels:
    fusion.parallax.plane_homography's K (R + t n^T / d) K^-1, kept as its two terms because it is linear in 1/d."""

    def __init__(self, k: np.ndarray, cur: CameraPose, ref: CameraPose,
                 before: Optional[np.ndarray] = None, after: Optional[np.ndarray] = None):
        before = np.eye(3) if before is None else before
        after = np.eye(3) if after is None else after
        hom, rot, _, _, d = plane_homography(k, cur, ref)
        rotation = k @ rot @ np.linalg.inv(k)
        self._a = after @ rotation @ before
        self._b = after @ ((hom - rotation) * d) @ before

    def __call__(self, inv_d: float) -> np.ndarray:
        out: np.ndarray = self._a + self._b * inv_d
        return out


def _levels(hom_at: _Homographies, centre_px: tuple[float, float], d_ground: float, cfg: SweepConfig) -> np.ndarray:
    """Candidate plane distances below the camera, ground first, evenly spaced in 1/d (the homography is
    linear in 1/d, so the window's centre moves about evenly along its epipolar line)."""
    d_top = (1.0 - cfg.top_share) * d_ground
    x = np.array([centre_px[0], centre_px[1], 1.0])
    ends = []
    for d in (d_ground, d_top):
        q = hom_at(1.0 / d) @ x
        ends.append(q[:2] / q[2] if q[2] > 0 else np.full(2, np.nan))
    span_px = float(np.hypot(*(ends[1] - ends[0])))
    if not np.isfinite(span_px):
        return np.array([d_ground])
    n = int(np.clip(np.ceil(span_px / cfg.step_px) + 1, 2, cfg.max_levels))
    return 1.0 / np.linspace(1.0 / d_ground, 1.0 / d_top, n)


def _zncc(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    x, y = a[mask], b[mask]
    x = x - x.mean()
    y = y - y.mean()
    den = float(np.sqrt(np.dot(x, x) * np.dot(y, y)))
    return float(np.dot(x, y)) / den if den > 0 else float("nan")


def sweep_plane(k: np.ndarray, cur: CameraPose, ref: CameraPose, ref_grey: np.ndarray, cur_window: np.ndarray,
                origin_rc: tuple[int, int], cfg: SweepConfig) -> SweepResult:
    """The plane (distance below the current camera, m) that best maps the keyframe onto the current window.

    ``k``: 3×3 intrinsics (OpenCV pixel centres) of both frames; ``ref_grey``: the whole keyframe; ``cur_window``:
    the current frame's window (uint8), whose top-left pixel is ``origin_rc`` (row, col) of the frame.
    """
    d_ground = cur.agl_m
    if not cfg.enabled:
        return SweepResult(d_ground, d_ground, float("nan"), float("nan"))
    s = cfg.scale
    h, w = cur_window.shape
    hs, ws = max(8, int(round(h * s))), max(8, int(round(w * s)))
    sy, sx = hs / h, ws / w
    small = cv2.resize(cur_window, (ws, hs), interpolation=cv2.INTER_AREA).astype(np.float32)
    ref_small = cv2.resize(ref_grey, (int(round(ref_grey.shape[1] * sx)), int(round(ref_grey.shape[0] * sy))),
                           interpolation=cv2.INTER_AREA).astype(np.float32)
    r0, c0 = origin_rc
    # Small window pixel -> full frame pixel (pixel centres: x_full = (x_small + 0.5) / s - 0.5 + c0), then the
    # plane's homography into the keyframe, then full keyframe pixel -> small keyframe pixel.
    to_full = np.array([[1.0 / sx, 0.0, 0.5 / sx - 0.5 + c0], [0.0, 1.0 / sy, 0.5 / sy - 0.5 + r0], [0.0, 0.0, 1.0]])
    to_small = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
    levels = _levels(_Homographies(k, cur, ref), (c0 + 0.5 * (w - 1), r0 + 0.5 * (h - 1)), d_ground, cfg)
    hom_small = _Homographies(k, cur, ref, to_full, to_small)
    scores = np.full(levels.size, np.nan)
    warps: list[Optional[np.ndarray]] = []
    for i, d in enumerate(levels):
        warped = cv2.warpPerspective(ref_small, hom_small(1.0 / float(d)), (ws, hs),
                                     flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=-1.0)
        inside = warped >= 0.0
        counted = inside.mean() >= cfg.min_overlap
        if counted:
            scores[i] = _zncc(small, warped, inside)
        warps.append(warped if counted else None)
    ground_score = float(scores[0])
    if not np.isfinite(scores).any():
        return SweepResult(d_ground, d_ground, float("nan"), ground_score)
    best = int(np.nanargmax(scores))
    gain = scores[best] - (ground_score if np.isfinite(ground_score) else -1.0)
    if best == 0 or not gain >= cfg.min_gain:
        return SweepResult(d_ground, d_ground, ground_score, ground_score)
    level = _refine(levels, scores, best)
    if d_ground - level < cfg.min_raise_m:
        return SweepResult(d_ground, d_ground, ground_score, ground_score)
    return SweepResult(level, d_ground, float(scores[best]), ground_score,
                       _verified(small, warps, best, cfg, (h, w)))


def _verified(small: np.ndarray, warps: list[Optional[np.ndarray]], best: int, cfg: SweepConfig,
              shape: tuple[int, int]) -> np.ndarray:
    """Pixels (window size) whose neighbourhood matches the levels next to ``best`` clearly better than every
    level farther away (not verified: no texture to tell, or a surface at another level), the mask shrunk by
    one sweep pixel so that a pixel next to an unverified one does not confirm either."""
    errors = np.full((len(warps),) + small.shape, np.inf, np.float32)     # per pixel, 3×3 mean |difference|
    box = np.ones((3, 3), np.uint8)
    for i, warped in enumerate(warps):
        if warped is not None:
            err = cv2.blur(np.abs(small - warped), (3, 3), borderType=cv2.BORDER_REPLICATE)
            errors[i] = np.where(cv2.erode((warped >= 0.0).view(np.uint8), box) > 0, err, np.inf)
    near = errors[max(0, best - 1) : best + 2].min(axis=0)
    far = np.concatenate([errors[: max(0, best - 1)], errors[best + 2 :]]).min(axis=0, initial=np.inf)
    ok = np.isfinite(near) & np.isfinite(far) & (near + cfg.verify_margin <= far) & (near <= cfg.verify_ratio * far)
    ok = cv2.erode(ok.view(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    out: np.ndarray = cv2.resize(ok, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST) > 0
    return out


def _refine(levels: np.ndarray, scores: np.ndarray, best: int) -> float:
    """The peak between levels: a parabola through the best score and its neighbours, in 1/d (the levels'
    even spacing), moved at most half a step."""
    if best + 1 >= levels.size or not np.isfinite(scores[best - 1 : best + 2]).all():
        return float(levels[best])
    lo, mid, hi = scores[best - 1 : best + 2]
    curve = lo - 2.0 * mid + hi
    shift = float(np.clip(0.5 * (lo - hi) / curve, -0.5, 0.5)) if curve < 0 else 0.0
    inv = 1.0 / levels
    return float(1.0 / (inv[best] + shift * (inv[best + 1] - inv[best])))
