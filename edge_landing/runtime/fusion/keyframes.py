"""The motion stage's keyframes and where it looks (ARCHITECTURE.md §11): a stored frame with its pose, the bounded
ring they are kept in and the one paired with the current frame, the window of the ground band DIS runs on, and a
keyframe resampled onto that window. Pure numpy/OpenCV; the ring is the caller's deque."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Deque, Mapping, Optional

import cv2
import numpy as np

from edge_landing.runtime.fusion.baseline import detectable_heights_m, window_probes
from edge_landing.runtime.fusion.motion_config import POSE_TELEMETRY, MotionConfig
from edge_landing.runtime.fusion.parallax import CameraPose, ned_points

__all__ = ["Keyframe", "ground_window", "pick_reference", "prune_keyframes", "PairNoise", "store_keyframe",
           "WindowGround", "window_ground", "warp_window"]


@dataclass(frozen=True)
class Keyframe:
    """A grey frame at the stage's size, its time (s, local clock) and camera pose, and where the pose came from.

    ``scale_agl_m``: the height above ground that set the metric scale of the frame (the telemetry's, or the one
    the images carried over when it was refused: fusion.image_motion.carried_height_m); NaN: not known.
    ``chroma``: its Cr, Cb at half the size (fusion.chroma; None: a grey camera)."""

    time_s: float
    grey: np.ndarray
    pose: CameraPose
    source: str = POSE_TELEMETRY
    scale_agl_m: float = math.nan
    chroma: Optional[np.ndarray] = None


def prune_keyframes(ring: Deque[Keyframe], time_s: float, history_s: float) -> None:
    """Drop keyframes older than ``history_s`` before ``time_s``, and any not before it (time went back)."""
    while ring and (time_s - ring[0].time_s > history_s or ring[0].time_s >= time_s):
        ring.popleft()


def store_keyframe(ring: Deque[Keyframe], item: Keyframe, config: MotionConfig) -> None:
    """Append ``item``, keeping keyframes at least ``history_s / max_frames`` apart and at most ``max_frames``:
    the newest frame replaces the previous one when that one is too close to its predecessor (the ring always
    holds the latest frame)."""
    gap = config.history_s / config.max_frames
    if len(ring) > 1 and ring[-1].time_s - ring[-2].time_s < gap:
        ring.pop()
    ring.append(item)
    while len(ring) > config.max_frames:
        ring.popleft()


@dataclass(frozen=True)
class WindowGround:
    """Where a window looks on the ground plane (local NED, m): the ground point at its centre, and how far its
    corners' ground points lie from it (``radius_m``, its footprint)."""

    centre_ne_m: np.ndarray
    radius_m: float

    def covers(self, point_ne_m: np.ndarray) -> bool:
        return bool(np.hypot(*(np.asarray(point_ne_m) - self.centre_ne_m)) <= self.radius_m)


def window_ground(pose: CameraPose, window: tuple[slice, slice], k_inv: np.ndarray) -> Optional[WindowGround]:
    """The ground footprint of ``window`` seen from ``pose`` (ground plane ``pose.agl_m`` below the camera); None
    when its centre's ray does not meet the ground. Corners above the horizon are left out of the radius."""
    rs, cs = window
    us = np.array([0.5 * (cs.start + cs.stop), cs.start, cs.stop, cs.start, cs.stop], np.float64)
    vs = np.array([0.5 * (rs.start + rs.stop), rs.start, rs.start, rs.stop, rs.stop], np.float64)
    pts, ahead = ned_points(pose, (k_inv @ np.vstack([us, vs, np.ones(5)]))[:2], np.ones(5))   # NaN: no ground
    if not ahead[0] > 0:
        return None
    centre = pts[:2, 0]
    spread = np.hypot(pts[0, 1:] - centre[0], pts[1, 1:] - centre[1])
    return WindowGround(centre, float(np.nanmax(spread)) if np.isfinite(spread).any() else 0.0)


class PairNoise:
    """What each keyframe's pairs gave: the flow noise (px, measured across the epipolar lines) of its pairs that
    failed (above ``max_plane_noise_px``), each with the ground its window looked at, and when a pair last held.

    A pair fails for the ground it looks at, not for its keyframe as a whole: one taken above a tall building sees
    the ground behind the roof's edge, and the same keyframe pairs well on open ground elsewhere. So a failure
    counts against its keyframe (:meth:`penalised`) only for a window whose ground centre lies within the failed
    window's footprint, and a pair of that keyframe that held there takes the failure back. A failure counts
    only while some pair held within ``history_s``: when every pair fails (heavy rain, a smeared feed) the
    cause is the conditions, and scoring each keyframe by the noise it gave would walk the choice, pair by pair,
    to the shortest baselines, which resolve nothing. Entries of keyframes no longer in the ring are dropped
    and each keyframe keeps at most ``MAX_PER_KEYFRAME`` failures, so the memory never outgrows the ring."""

    MAX_PER_KEYFRAME = 4

    def __init__(self) -> None:
        self.failed: dict[float, list[tuple[float, Optional[WindowGround]]]] = {}   # keyframe time -> failures
        self.held_s = -math.inf                 # time of the last pair that held

    def clear(self) -> None:
        self.failed.clear()
        self.held_s = -math.inf

    def remember(self, ring: Deque[Keyframe], ref_time_s: float, time_s: float, noise_px: float,
                 ground: Optional[WindowGround], config: MotionConfig) -> None:
        """Record the pair made at ``time_s`` with the keyframe at ``ref_time_s``, whose noise was ``noise_px``,
        over the window whose ground is ``ground`` (None: not known; such a failure counts for every window)."""
        here = [] if ground is None else [f for f in self.failed.get(ref_time_s, [])
                                          if f[1] is None or not f[1].covers(ground.centre_ne_m)]
        if noise_px > config.max_plane_noise_px:
            self.failed[ref_time_s] = (here + [(noise_px, ground)])[-self.MAX_PER_KEYFRAME:]
        else:
            if here:
                self.failed[ref_time_s] = here
            else:
                self.failed.pop(ref_time_s, None)
            self.held_s = time_s
        kept = {it.time_s for it in ring} | {ref_time_s}
        for stale in [t for t in self.failed if t not in kept]:
            del self.failed[stale]

    def penalised(self, time_s: float, ground: Optional[WindowGround], config: MotionConfig) -> Mapping[float, float]:
        """The keyframes to score by their noise for a window over ``ground`` at ``time_s`` (the worst of their
        failures that covered it): none unless a pair held within ``history_s`` before it."""
        if not 0.0 <= time_s - self.held_s <= config.history_s:
            return {}
        out: dict[float, float] = {}
        for t, fails in self.failed.items():
            hits = [n for n, g in fails if g is None or ground is None or g.covers(ground.centre_ne_m)]
            if hits:
                out[t] = max(hits)
        return out


def pick_reference(ring: Deque[Keyframe], pose: CameraPose, window: tuple[slice, slice], k_cv: np.ndarray,
                   k_inv: np.ndarray, size_hw: tuple[int, int], config: MotionConfig,
                   failed_noise_px: Optional[Mapping[float, float]] = None
                   ) -> tuple[Optional[Keyframe], float, str]:
    """(keyframe, the height it detects, why none) for the current frame at ``pose``: the newest keyframe that
    detects ``enough_detect_m`` with margin, else the most sensitive one.

    All stored frames are scored at once at a few probe pixels of the window: the smallest height they could
    detect there (median over the probes the keyframe still sees). Hovering (no baseline) scores inf: no
    keyframe, no evidence. The score assumes the flow noise floor (``flow_noise_px``); a keyframe whose last
    pair failed (``failed_noise_px``: its time -> that pair's noise) is scored with the noise
    it gave (PairNoise.penalised). A keyframe taken above a tall building sees the ground behind the roof's edge,
    and the longest baseline, best on paper, would otherwise be picked again for every frame of a hover.
    """
    if not ring:
        return None, math.inf, "no earlier frame yet"
    items = list(ring)
    det = detectable_heights_m(pose, [it.pose for it in items], window_probes(window), k_cv, k_inv, size_hw, config)
    if failed_noise_px:
        det = det * np.array([max(1.0, failed_noise_px.get(it.time_s, 0.0) / config.flow_noise_px) for it in items])
    if not np.isfinite(det).any():
        return None, math.inf, "no keyframe with a usable baseline overlaps the current view (hovering?)"
    # A longer baseline than needed only adds occlusion and resampling blur.
    enough = np.flatnonzero(det <= config.enough_detect_m)
    pick = int(enough[-1]) if enough.size else int(np.argmin(det))
    return items[pick], float(det[pick]), ""


def warp_window(src: np.ndarray, hom: np.ndarray, window: tuple[slice, slice]) -> np.ndarray:
    """``src`` (a keyframe, grey) resampled onto the current frame's ``window`` by ``hom`` (current frame pixel ->
    ``src`` pixel): only the window is warped, its pixel (x, y) being (x + c0, y + r0) of the frame."""
    rs, cs = window
    shift = np.array([[1.0, 0.0, cs.start], [0.0, 1.0, rs.start], [0.0, 0.0, 1.0]])
    out: np.ndarray = cv2.warpPerspective(src, hom @ shift, (cs.stop - cs.start, rs.stop - rs.start),
                                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
    return out


def ground_window(pose: CameraPose, focus: Optional[np.ndarray], norm: np.ndarray, size_hw: tuple[int, int],
                  k_cv: np.ndarray, config: MotionConfig, scan: int) -> Optional[tuple[slice, slice]]:
    """Rows and columns DIS runs on: the ground band within ``max_range_m``, cropped to ``window_hw``, centred on
    ``focus`` (a candidate spot, local NED) when it is in front of the camera, else at scan position ``scan``
    (0-5). ``norm``: the stage's normalised pixel coordinates (2×H×W); None when no ground is in range."""
    h, w = size_hw
    n = pose.r_nc.T @ np.array([0.0, 0.0, 1.0])
    # Rows get nearer going down (camera below the horizon): test every row at five columns at once.
    xs = norm[0][0][np.linspace(0, w - 1, 5).astype(int)][None, :]
    ys = norm[1][:, :1]
    nx = n[0] * xs + n[1] * ys + n[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.where(nx > 0, pose.agl_m / nx, np.nan)
    r = pose.r_nc
    pn = (r[0, 0] * xs + r[0, 1] * ys + r[0, 2]) * lam
    pe = (r[1, 0] * xs + r[1, 1] * ys + r[1, 2]) * lam
    with np.errstate(invalid="ignore"):
        rows = np.flatnonzero(np.any(np.hypot(pn, pe) <= config.max_range_m, axis=1))
    if rows.size == 0 or h - int(rows[0]) < 16:
        return None
    row0 = max(0, int(rows[0]) - 8)                      # DIS patches need a little context
    wh, ww = min(config.window_hw[0], h - row0), min(config.window_hw[1], w)
    # No candidate spot: scan the ground band, one window position per frame pair (3 columns × 2 rows), so that
    # the evidence (kept for tens of seconds) covers where a spot may be proposed later, instead of always the
    # same patch below the vehicle.
    cu = (0.5 + (scan % 3 - 1) * 0.34) * w
    cv = h - 0.5 * wh if scan < 3 else row0 + 0.5 * wh
    if focus is not None:
        cam = pose.r_nc.T @ (np.asarray(focus, np.float64) - pose.position_ned_m)
        if cam[2] > 0:
            cu, cv = k_cv[0, 0] * cam[0] / cam[2] + k_cv[0, 2], k_cv[1, 1] * cam[1] / cam[2] + k_cv[1, 2]
    c0 = int(np.clip(round(cu - ww / 2), 0, w - ww))
    r0 = int(np.clip(round(cv - wh / 2), row0, h - wh))
    return slice(r0, r0 + wh), slice(c0, c0 + ww)
