"""The camera's orientation checked against the images: is the camera turned as the mount and the telemetry say?
(ARCHITECTURE.md §11)

Between two frames with telemetry poses, the ground's plane-induced homography (normalised coordinates, current ->
reference) is A = R + t nᵀ/d: R the relative rotation, t the translation in the reference camera's frame, n the
ground's normal in the current camera's frame. Tracked ground features and RANSAC give A up to scale
(fusion.image_motion.match_ground); the middle singular value of a plane homography is 1, which fixes the scale,
and A − R is then of rank one: its singular vectors are t's and n's directions *as the camera saw them*. The poses
predict both from the telemetry and the mount. If the camera is turned by a small rotation δ from what they say
(r_nc_true = r_nc δ: a mount off by degrees, or an attitude with a steady bias), the seen directions are δᵀ times
the predicted ones, whatever the scene: the ground's normal gives the camera's tilt, the direction of travel its
pitch and pan. R depends on δ only through the change of attitude between the two frames (small).

The dominant plane of a pair may be a façade: planes are fitted one after another and the one whose normal is
nearest the predicted ground's (within ``MAX_NORMAL_DEG``) is kept. Each pair gives δ alone (two directions fix a
rotation); the largest set of pairs agreeing within ``agree_deg`` are the ground's. δ is then fitted to them by
linearised least squares together with the ground's slope (``refine_with_slope``): sloped ground tilts the normal
as a turned camera would, but the direction of travel has no slope in it, and a second heading separates the
rest. What the pairs cannot tell stays uncertain: the estimate is read as a fixed mount, angle by angle with its
σ (``MountEstimate.axes``), and only an angle off by more than ``warn_deg`` and 2σ calls for attention. A mount
off by 2-3° leaves motion geometry unable to confirm anything (its plane is wrong by metres), which the check
then explains.

Pure numpy/OpenCV, no I/O; memory: the newest ``max_pairs`` pairs of directions (a dozen numbers each).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Deque, Iterator, Optional, Sequence

import cv2
import numpy as np

from edge_landing.runtime.core.camera import Mount
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.fusion.image_motion import GroundMatches, ImagePoseConfig, match_ground
from edge_landing.runtime.fusion.keyframes import Keyframe
from edge_landing.runtime.fusion.motion_config import POSE_TELEMETRY
from edge_landing.runtime.fusion.turn_fit import (
    PairDirections,
    agreement_deg,
    angles_deg,
    pair_turns,
    refine_with_slope,
    solve_turn,
)

__all__ = ["MountCheck", "MountCheckConfig", "MountEstimate", "PairDirections", "pair_directions"]

_DOWN = np.array([0.0, 0.0, 1.0])
MAX_PLANES = 3          # planes looked for among a pair's tracks (the ground, façades)
MAX_NORMAL_DEG = 20.0   # a plane whose normal is farther than this from the ground's is not the ground
_HEADING_BIN_DEG = 45.0


@dataclass(frozen=True)
class MountCheckConfig:
    """Settings of the mount check. Seconds, degrees, ratios of the height above ground."""

    enabled: bool = True
    interval_s: float = 0.5           # a pair at most this often until ``settle_pairs`` are kept ...
    settled_interval_s: float = 5.0   # ... then this often
    settle_pairs: int = 60
    min_baseline_ratio: float = 0.1   # shorter baselines give the direction of travel poorly
    max_baseline_ratio: float = 0.6   # longer ones overlap too little
    min_pairs: int = 20               # an estimate needs this many agreeing pairs
    agree_deg: float = 5.0            # pairs whose turn is within this of the consensus are the ground's (a
                                      # sloped field turns each heading's pairs by its slope: a few degrees)
    max_pairs: int = 240
    work_width_px: int = 320          # frames are tracked at most this wide (a quarter of the pixels of 640×480:
                                      # a quarter of the cost; the pairs' spread is averaged out anyway)
    warn_deg: float = 1.5             # said as a problem when the camera is turned more than this, beyond 2 σ
    # Corners tracked per pair: the cost is the tracking (two pyramidal LK passes per corner); 150 are plenty
    # for one plane's homography.
    features: ImagePoseConfig = ImagePoseConfig(max_features=150)

    def __post_init__(self) -> None:
        for name in ("interval_s", "settled_interval_s", "min_baseline_ratio", "agree_deg", "warn_deg"):
            if not getattr(self, name) > 0:
                raise InputError(f"mount check {name} must be > 0, got {getattr(self, name)}")
        if not self.min_baseline_ratio < self.max_baseline_ratio:
            raise InputError(f"mount check baselines: min {self.min_baseline_ratio} must be below max "
                             f"{self.max_baseline_ratio}")
        if not 3 <= self.min_pairs <= self.max_pairs:
            raise InputError(f"mount check needs 3 <= min_pairs <= max_pairs, got {self.min_pairs}, {self.max_pairs}")


# The pairs' own spread misses what the ground's shape adds (it is not one plane; the slope fitted is one number):
# on the sim's flights the estimate was up to 0.5° off where its spread said 0.1°. Said with every figure.
GROUND_SHAPE_DEG = 0.5


def _with_ground(sigma_deg: float) -> float:
    return math.hypot(sigma_deg, GROUND_SHAPE_DEG)


@dataclass(frozen=True)
class MountEstimate:
    """δ (3×3, camera frame: the camera is turned r_nc @ δ) and the covariance of its rotation vector (rad²),
    for the fixed ``mount`` it was measured against; the pairs that agree on it among those kept, and the
    directions of flight (45° bins) they came from."""

    delta: np.ndarray
    cov: np.ndarray
    mount: Mount
    pairs: int
    kept: int
    headings: int
    ground_slope_deg: float = 0.0    # the ground's tilt fitted with it (sloped ground tilts the normal too)
    warn_deg: float = 1.5            # MountCheckConfig.warn_deg

    @property
    def turn_deg(self) -> float:
        """How far the camera is turned from what the poses say, in degrees."""
        return math.degrees(float(np.linalg.norm(cv2.Rodrigues(self.delta)[0])))

    def corrected(self, delta: Optional[np.ndarray] = None) -> Mount:
        """The fixed mount that makes the poses agree with the images: body <- camera is the mount's, then δ."""
        turn = self.delta if delta is None else delta
        return Mount.from_body_from_gimbal(self.mount.body_from_camera() @ turn @ np.linalg.inv(_level()))

    def axes(self) -> list[tuple[str, float, float, float]]:
        """Per mount angle: (name, given °, measured °, 1-σ ° from the pairs' spread; ``describe`` adds
        ``GROUND_SHAPE_DEG``). Some combinations are not measured at all (roll about the direction of flight, on
        one heading over sloped ground): their σ stays near the prior's."""
        names = ("pitch", "roll", "yaw")

        def angles(turn: np.ndarray) -> np.ndarray:
            m = self.corrected(turn)
            return np.degrees([m.pitch_rad, m.roll_rad, m.yaw_rad])

        base, eps = angles(self.delta), 1e-4
        jac = np.stack([(angles(cv2.Rodrigues(eps * np.eye(3)[i].reshape(3, 1))[0] @ self.delta) - base) / eps
                        for i in range(3)], axis=1)                       # ° per rad of the turn's rotation vector
        sigma = np.sqrt(np.maximum(np.diag(jac @ self.cov @ jac.T), 0.0))
        given = np.degrees([self.mount.pitch_rad, self.mount.roll_rad, self.mount.yaw_rad])
        return [(n, float(g), float(b), float(sg)) for n, g, b, sg in zip(names, given, base, sigma)]

    @property
    def attention(self) -> bool:
        """An angle off by more than ``warn_deg`` and by more than 2 σ (with the ground's share): worth saying."""
        return any(abs(b - g) > max(self.warn_deg, 2.0 * _with_ground(sg)) for _, g, b, sg in self.axes())

    def describe(self) -> str:
        angles = ", ".join(f"{name} {b:.1f}° ± {_with_ground(sg):.1f}° (given {g:.1f}°)"
                           for name, g, b, sg in self.axes())
        return (f"camera orientation measured from the images ({self.pairs} of {self.kept} frame pairs agree, "
                f"{self.headings} direction(s) of flight, ground sloped {self.ground_slope_deg:.1f}°): turned "
                f"{self.turn_deg:.1f}° from the mount and attitude; as a fixed mount: {angles}")


def _level() -> np.ndarray:
    """body <- camera for a level, forward-looking camera (camera x right, y down, z forward)."""
    return Mount(pitch_rad=0.0).body_from_camera()


def _shrunk(kf: Keyframe, width_px: int) -> Keyframe:
    w = kf.grey.shape[1]
    if w <= width_px:
        return kf
    h = max(1, int(round(kf.grey.shape[0] * width_px / w)))
    return Keyframe(kf.time_s, cv2.resize(kf.grey, (width_px, h), interpolation=cv2.INTER_AREA), kf.pose, kf.source)


def _shrunk_k(k: np.ndarray, width_px: int, work_px: int) -> np.ndarray:
    """Intrinsics (OpenCV's pixel-centre convention) of a frame ``width_px`` wide resized to ``work_px``."""
    if width_px <= work_px:
        return k
    f = work_px / width_px
    out: np.ndarray = k.copy()
    out[0, 0], out[1, 1] = k[0, 0] * f, k[1, 1] * f
    out[0, 2], out[1, 2] = (k[0, 2] + 0.5) * f - 0.5, (k[1, 2] + 0.5) * f - 0.5
    return out


def pair_directions(ref: Keyframe, cur: Keyframe, k: np.ndarray, body_heading_rad: float,
                    config: ImagePoseConfig) -> tuple[Optional[PairDirections], str]:
    """The directions one pair of keyframes predicts and shows (None and why when it cannot tell); never raises."""
    try:
        return _pair_directions(ref, cur, np.asarray(k, np.float64), body_heading_rad, config)
    except (cv2.error, np.linalg.LinAlgError, ValueError) as exc:   # per-frame path: a reason, never a raise
        return None, f"degenerate: {type(exc).__name__}"


def _pair_directions(ref: Keyframe, cur: Keyframe, k: np.ndarray, heading: float, cfg: ImagePoseConfig
                     ) -> tuple[Optional[PairDirections], str]:
    r_ref, r_cur = ref.pose.r_nc, cur.pose.r_nc
    rot = r_ref.T @ r_cur
    baseline = cur.pose.position_ned_m - ref.pose.position_ned_m
    t_pred = r_ref.T @ baseline
    n_pred = r_cur.T @ _DOWN
    d = float(cur.pose.agl_m)
    m = match_ground(ref.grey, cur.grey, k, rot, t_pred, n_pred, d, cfg)
    if m.homography is None:
        return None, m.reason or "no homography"
    # The dominant plane may be a façade (a street between buildings): the planes are found one after another,
    # and the one whose normal is nearest the ground's, as the poses predict it, is the ground.
    best: Optional[tuple[float, np.ndarray]] = None
    k_inv = np.linalg.inv(k)
    for inl in _planes(m, cfg):
        a = _plane_homography(m.cur_px[inl], m.ref_px[inl], k, k_inv, rot)
        if a is None:
            continue
        n_seen = np.linalg.svd(a - rot)[2][0]
        angle = math.degrees(math.acos(min(1.0, abs(float(n_seen @ n_pred)))))
        if best is None or angle < best[0]:
            best = (angle, a)
    if best is None or best[0] > MAX_NORMAL_DEG:
        return None, "no ground plane among the tracked features" if best is None else \
            f"no plane within {MAX_NORMAL_DEG:g}° of the ground's (nearest {best[0]:.0f}°)"
    return PairDirections(best[1], rot, t_pred / np.linalg.norm(t_pred), n_pred, heading, r_cur), ""


def _planes(m: GroundMatches, cfg: ImagePoseConfig) -> Iterator[np.ndarray]:
    """Indices of the matches on each plane, up to ``MAX_PLANES``: the dominant one match_ground already found,
    then RANSAC again on what no plane took yet."""
    inl = np.flatnonzero(m.inliers)
    left = np.ones(m.cur_px.shape[0], bool)
    for k in range(MAX_PLANES):
        if k > 0:
            if int(left.sum()) < cfg.min_inliers:
                return
            idx = np.flatnonzero(left)
            hom, mask = cv2.findHomography(m.cur_px[idx], m.ref_px[idx], cv2.RANSAC, cfg.ransac_px, maxIters=500,
                                           confidence=0.995)
            if hom is None or mask is None:
                return
            inl = idx[mask.reshape(-1).astype(bool)]
        if inl.size < cfg.min_inliers:
            return
        left[inl] = False
        yield inl


def _plane_homography(cur_px: np.ndarray, ref_px: np.ndarray, k: np.ndarray, k_inv: np.ndarray, rot: np.ndarray
                      ) -> Optional[np.ndarray]:
    """The normalised homography of one plane's matches, scaled to middle singular value 1 and signed to keep the
    plane in front of the camera; None when it is not one plane seen from two places."""
    hom, _ = cv2.findHomography(cur_px, ref_px, 0)      # least squares on the plane's inliers
    if hom is None:
        return None
    a = k_inv @ hom @ k
    a = a / np.linalg.svd(a, compute_uv=False)[1]
    xc = np.hstack([cur_px.astype(np.float64), np.ones((cur_px.shape[0], 1))]) @ k_inv.T
    if np.median((xc @ a.T)[:, 2]) < 0:
        a = -a
    s = np.linalg.svd(a - rot, compute_uv=False)
    out: Optional[np.ndarray] = a if s[0] > 0 and s[1] <= 0.3 * s[0] else None
    return out


class MountCheck:
    """Pairs of the motion stage's keyframes, now and then; the camera's turn from what the poses say."""

    def __init__(self, config: MountCheckConfig, k: np.ndarray, mount: Mount):
        self.config = config
        self.k = np.asarray(k, np.float64)
        self.mount = mount                     # the fixed mount the poses were made with (the estimate's reference)
        self.pairs: Deque[PairDirections] = deque(maxlen=config.max_pairs)
        self._last_s = -math.inf
        self.last_reason = ""

    def reset(self) -> None:
        self.pairs.clear()
        self._last_s, self.last_reason = -math.inf, ""

    def due(self, time_s: float) -> bool:
        cfg = self.config
        every = cfg.interval_s if len(self.pairs) < cfg.settle_pairs else cfg.settled_interval_s
        return cfg.enabled and not 0.0 <= time_s - self._last_s < every

    def add(self, keyframes: Sequence[Keyframe], heading_rad: float) -> bool:
        """Pair the newest keyframe with the newest older one at a useful baseline; True when a pair was kept."""
        if len(keyframes) < 2:
            return False
        cur = keyframes[-1]
        self._last_s = cur.time_s
        ref = self._reference(keyframes)
        if ref is None:
            self.last_reason = "no keyframe at a useful baseline"
            return False
        got, why = pair_directions(_shrunk(ref, self.config.work_width_px), _shrunk(cur, self.config.work_width_px),
                                   _shrunk_k(self.k, cur.grey.shape[1], self.config.work_width_px), heading_rad,
                                   self.config.features)
        self.last_reason = why
        if got is not None:
            self.pairs.append(got)
        return got is not None

    def _reference(self, keyframes: Sequence[Keyframe]) -> Optional[Keyframe]:
        cur, cfg = keyframes[-1], self.config
        if cur.source != POSE_TELEMETRY or not np.all(np.isfinite(cur.pose.position_ned_m)):
            return None
        agl = float(cur.pose.agl_m)
        for ref in reversed(keyframes[:-1]):
            if ref.source != POSE_TELEMETRY:
                return None
            ratio = float(np.linalg.norm(cur.pose.position_ned_m - ref.pose.position_ned_m)) / agl
            if ratio > cfg.max_baseline_ratio:
                return None
            if ratio >= cfg.min_baseline_ratio:
                return ref
        return None

    def estimate(self) -> Optional[MountEstimate]:
        """The camera's turn from the pairs kept (None with fewer than ``min_pairs`` agreeing); never raises."""
        try:
            return self._estimate()
        except (cv2.error, np.linalg.LinAlgError, ValueError) as exc:   # per-frame path: a reason, never a raise
            self.last_reason = f"no estimate: {type(exc).__name__}"
            return None

    def _estimate(self) -> Optional[MountEstimate]:
        cfg = self.config
        pairs = list(self.pairs)
        if len(pairs) < cfg.min_pairs:
            return None
        turns = pair_turns(pairs)
        # The consensus: the pair whose turn the most others agree with, then every pair that agrees with it.
        agree = agreement_deg(turns) <= cfg.agree_deg
        members = agree[int(np.argmax(agree.sum(axis=1)))]
        delta = solve_turn([p for p, m in zip(pairs, members) if m])
        for _ in range(2):   # the relative rotations read with the turn found so far, and the agreeing pairs again
            turns = pair_turns(pairs, delta)
            members = angles_deg(delta, turns) <= cfg.agree_deg
            if int(members.sum()) < cfg.min_pairs:
                return None
            delta = solve_turn([p for p, m in zip(pairs, members) if m], delta)
        delta, cov, slope = refine_with_slope([p for p, m in zip(pairs, members) if m], delta)
        bins = {int(math.floor(math.degrees(p.heading_rad) % 360.0 / _HEADING_BIN_DEG))
                for p, m in zip(pairs, members) if m}
        return MountEstimate(delta, cov, self.mount, int(members.sum()), len(pairs), len(bins), slope, cfg.warn_deg)
