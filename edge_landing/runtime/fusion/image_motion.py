"""Image-only relative pose: the camera's translation between two frames from the images, the attitudes and the
height above ground, for motion geometry when telemetry has no position (ARCHITECTURE.md §11).

Frames: camera = OpenCV (x right, y down, z forward), world = local NED. ``r_nc`` is the NED <- camera rotation
of a frame (from the attitude and the mount), ``k`` the 3×3 intrinsics in OpenCV's pixel-centre convention.

Ground points seen from the current camera (c) and a reference one (r) obey the plane-induced homography
(normalised coordinates) x_r ~ (R + t n^T / d) x_c, with R = R_r^T R_c (known from the attitudes),
n = R_c^T (0, 0, 1) (world down in camera c), d = the current height above ground and t = R_r^T (p_c - p_r)
the unknown translation. With y = R x_c and a = n^T x_c / d, each match (x_c, x_r = (u, v)) gives two
equations that are linear in t:
    a t_x - u a t_z = u y_z - y_x,      a t_y - v a t_z = v y_z - y_y.
Features are tracked (goodFeaturesToTrack + pyramidal LK, forward-backward checked) on the ground, a RANSAC
homography (cv2.findHomography) rejects what does not lie on one plane (obstacles, bad tracks), and t is solved
by weighted least squares on the inliers with R fixed. The metric scale comes only from ``d``: a relative
error ε of the height above ground scales t, and hence every measured height, by 1 + ε, which
``ImagePoseConfig.agl_sigma_rel`` accounts for. The residual of the fit is the pose's quality: the 1-σ
translation error (from the fit's covariance) and the reprojection residual in pixels.

Pure numpy/OpenCV, no I/O, no state: every call is bounded by ``max_features``. Never raises: a failure is an
``ImagePose`` with ``ok=False`` and a ``reason``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Optional

import cv2
import numpy as np

from edge_landing.runtime.core.errors import InputError

_DOWN = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class ImagePoseConfig:
    """Settings of the image-only pose. Pixels at the frame's size, metres."""

    max_features: int = 400              # corners tracked per estimate (bounds the cost)
    min_distance_px: int = 6             # between corners
    quality: float = 0.005               # goodFeaturesToTrack's relative corner quality
    lk_window_px: int = 21
    lk_levels: int = 3                   # pyramid levels: shifts of ~2^levels × window / 2 pixels are followed
    max_fb_error_px: float = 0.5         # forward-backward tracking disagreement beyond this drops the track
    ransac_px: float = 1.0               # RANSAC reprojection threshold of the homography
    min_inliers: int = 25                # fewer inliers: too few features
    min_inlier_share: float = 0.4        # of the tracked features; less: no dominant ground plane
    max_residual_px: float = 1.0         # median residual of the attitude-constrained fit; more: the attitude
                                         # does not explain the images (bad attitude, time skew, moving scene)
    max_range_m: float = 120.0           # features on ground farther than this are not used
    agl_sigma_rel: float = 0.02          # 1-σ relative error of the height above ground (the metric scale)
    # The fit's covariance assumes independent track errors; on the sim pairs the actual errors were up to
    # twice the stated σ (0.043 m against 0.02 m over 6.4 m): σ is inflated by this factor.
    sigma_inflation: float = 2.0
    # A height above ground that differs from the one the images carry over from the previous frame by more than
    # this (+ 3 σ of the pair's climb) read something that is not the ground: a rangefinder over a tree or a car
    # (the carried height is used instead); refused for longer than ``agl_refused_max_s``, the ground itself
    # changed level, and the odometry starts over. Things on the ground make a rangefinder read short, never long,
    # so a height that stays longer than the carried one for ``agl_longer_max_s`` means the carried height itself
    # was read off something standing there (a tree under the chain's first frames: every step 0.87 of the truth,
    # suburban 6930), and the odometry starts over at once, at the longer height. The short wait lets one
    # glitching reading pass: starting over at it would carry a wrong height instead.
    # A shorter height is refused for longer than ``agl_refused_max_s`` only once the vehicle has also moved
    # ``agl_refused_travel_m`` across the ground since: the ground's level changes under a vehicle only as it flies
    # over it, and one hovering over a tree would otherwise take the crown for the ground (suburban 6930's hover:
    # 53.7 m read against 60.6 m, and the odometry started over at the crown's height).
    agl_gate_m: float = 0.5
    agl_refused_max_s: float = 2.0
    agl_refused_travel_m: float = 8.0
    agl_longer_max_s: float = 0.25
    # A chained step that changes the velocity faster than this (+ 3 σ) is no flight: the odometry starts over. A
    # flat roof taken for the ground scales the translation by the ratio of the heights (urban 1041 without
    # position: 2.07 -> 5.45 m per frame at 10 frames/s, 340 m/s², and the frames drifted 10 m in 0.3 s). 5 g is
    # far beyond a multirotor (about 17 m/s² horizontally at a 60° tilt) and above the sim flights' phase changes
    # (up to 42 m/s² in one frame); it catches a wrong plane's onset, not a slow drift.
    max_accel_mps2: float = 50.0

    def __post_init__(self) -> None:
        if self.max_features < 8 or self.min_inliers < 8:
            raise InputError(f"image pose needs at least 8 features and inliers, got max_features="
                             f"{self.max_features}, min_inliers={self.min_inliers}")
        for name in ("min_distance_px", "quality", "lk_window_px", "max_fb_error_px", "ransac_px",
                     "max_residual_px", "max_range_m"):
            if not getattr(self, name) > 0:
                raise InputError(f"image pose {name} must be > 0, got {getattr(self, name)}")
        if not (self.agl_gate_m > 0 and self.agl_refused_max_s >= 0 and self.agl_longer_max_s >= 0
                and self.agl_refused_travel_m >= 0):
            raise InputError(f"image pose agl_gate_m must be > 0, agl_refused_max_s, agl_refused_travel_m and "
                             f"agl_longer_max_s >= 0, got {self.agl_gate_m}, {self.agl_refused_max_s}, "
                             f"{self.agl_refused_travel_m}, {self.agl_longer_max_s}")
        if not self.max_accel_mps2 > 0:
            raise InputError(f"image pose max_accel_mps2 must be > 0, got {self.max_accel_mps2}")
        if not self.sigma_inflation >= 1:
            raise InputError(f"image pose sigma_inflation must be >= 1, got {self.sigma_inflation}")
        if not 0 < self.min_inlier_share <= 1 or not 0 <= self.agl_sigma_rel < 0.3:
            raise InputError(f"image pose min_inlier_share must be in (0, 1] and agl_sigma_rel in [0, 0.3), got "
                             f"{self.min_inlier_share}, {self.agl_sigma_rel}")


@dataclass(frozen=True)
class ImagePose:
    """Result of one estimate. ``delta_ned_m``: p_current - p_reference in local NED (metres), NaN when not ok.

    ``sigma_m``: 1-σ error of the translation's worst direction from the fit (not counting the height's scale
    error, ``scale_sigma_rel``); ``inliers`` / ``inlier_share``: RANSAC ground-plane inliers among the tracked
    features; ``residual_px``: median reprojection residual of the attitude-constrained model on them.
    """

    ok: bool
    reason: str = ""
    delta_ned_m: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    sigma_m: float = math.inf
    scale_sigma_rel: float = 0.0
    inliers: int = 0
    inlier_share: float = 0.0
    residual_px: float = math.nan
    features: int = 0
    cov_ref_m2: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.inf))   # of t, reference camera

    @staticmethod
    def failed(reason: str, **figures: float) -> ImagePose:
        return ImagePose(False, reason, **figures)  # type: ignore[arg-type]

    def rescaled(self, factor: float) -> ImagePose:
        """The same estimate at another metric scale (a height above ground ``factor`` times the one used)."""
        return replace(self, delta_ned_m=self.delta_ned_m * factor, sigma_m=self.sigma_m * factor,
                       cov_ref_m2=self.cov_ref_m2 * factor ** 2)

    def describe(self) -> str:
        if not self.ok:
            return f"image pose failed: {self.reason}"
        return (f"image pose: {self.inliers}/{self.features} inliers, residual {self.residual_px:.2f} px, "
                f"σ {self.sigma_m:.2f} m")


def carried_height_m(reference_height_m: float, delta_ned_m: np.ndarray, used_height_m: float) -> float:
    """The current frame's height above the ground plane that the images carry over from the reference frame's.

    ``delta_ned_m`` (p_cur - p_ref) was estimated at the metric scale ``used_height_m``; its climb relative to that
    height is scale-free: d_ref - d_cur = Δ_down, so d_cur = d_ref / (1 + Δ_down / d_used). NaN when either
    height is unusable."""
    if not (math.isfinite(reference_height_m) and math.isfinite(used_height_m) and used_height_m > 0):
        return math.nan
    ratio = 1.0 + float(delta_ned_m[2]) / used_height_m
    return reference_height_m / ratio if ratio > 0 else math.nan


def estimate_translation(ref_grey: np.ndarray, cur_grey: np.ndarray, k: np.ndarray, r_nc_ref: np.ndarray,
                         r_nc_cur: np.ndarray, agl_cur_m: float, config: ImagePoseConfig,
                         prior_delta_ned_m: Optional[np.ndarray] = None
                         ) -> ImagePose:
    """Translation p_cur - p_ref (NED, m) from two grey uint8 frames of the same size; never raises.

    ``prior_delta_ned_m`` (optional) seeds the tracker with the plane homography it implies (long baselines).
    """
    try:
        return _estimate(ref_grey, cur_grey, np.asarray(k, np.float64), np.asarray(r_nc_ref, np.float64),
                         np.asarray(r_nc_cur, np.float64), float(agl_cur_m), config, prior_delta_ned_m)
    except (cv2.error, np.linalg.LinAlgError, ValueError) as exc:   # per-frame path: a reason, never a raise
        return ImagePose.failed(f"degenerate: {type(exc).__name__}: {str(exc).splitlines()[0][:80]}")


def _estimate(ref: np.ndarray, cur: np.ndarray, k: np.ndarray, r_ref: np.ndarray, r_cur: np.ndarray, d: float,
              cfg: ImagePoseConfig, prior: Optional[np.ndarray]) -> ImagePose:
    if ref.shape != cur.shape or ref.ndim != 2 or ref.dtype != np.uint8 or cur.dtype != np.uint8:
        return ImagePose.failed(f"frames must be grey uint8 of one size, got {ref.shape} {ref.dtype} and "
                                f"{cur.shape} {cur.dtype}")
    if not (math.isfinite(d) and d > 0):
        return ImagePose.failed(f"height above ground {d} m unusable")
    k_inv = np.linalg.inv(k)
    rot = r_ref.T @ r_cur
    n = r_cur.T @ _DOWN
    t_prior = np.zeros(3) if prior is None or not np.all(np.isfinite(prior)) else r_ref.T @ np.asarray(prior)
    m = match_ground(ref, cur, k, rot, t_prior, n, d, cfg)
    n_feat = m.features
    if m.reason:
        return ImagePose.failed(m.reason, features=n_feat, inliers=int(m.inliers.sum()), inlier_share=m.inlier_share)
    cur_pts, tracked, inl, share = m.cur_px, m.ref_px, m.inliers, m.inlier_share
    xc, xr = _normalised(k_inv, cur_pts[inl]), _normalised(k_inv, tracked[inl])
    f = 0.5 * (k[0, 0] + k[1, 1])
    t, res_px, cov = _solve_t(xc, xr, rot, n, d, f, cfg.ransac_px)
    n_in = int(inl.sum())
    figures = dict(features=n_feat, inliers=n_in, inlier_share=share)
    if t is None:
        return ImagePose.failed("degenerate: the ground features do not constrain the translation", **figures)
    med = float(np.median(res_px))
    if med > cfg.max_residual_px:
        return ImagePose.failed(f"inconsistent with the attitude: median residual {med:.2f} px > "
                                f"{cfg.max_residual_px} px", residual_px=med, **figures)
    # The climb is not checked here against the change of the height above ground: that height is measured
    # below the vehicle and jumps by metres over cars and roofs (it broke the chain ten times on one flight).
    # The motion stage carries the height through the chain instead (carried_height_m).
    delta = r_ref @ t
    cov = cov * cfg.sigma_inflation ** 2
    sigma = float(math.sqrt(max(float(np.max(np.linalg.eigvalsh(cov))), 0.0)))
    return ImagePose(True, "", delta, sigma, cfg.agl_sigma_rel, n_in, share, med, n_feat, cov)


@dataclass(frozen=True)
class GroundMatches:
    """Ground features of the current frame (``cur_px``, N×2 pixels) and where they lie in the reference frame
    (``ref_px``), with the RANSAC homography current -> reference they fit (``homography``, None when none did)
    and which of them fit it (``inliers``). ``reason`` is empty when the matches are usable (enough features,
    tracks and inliers: ImagePoseConfig's thresholds)."""

    cur_px: np.ndarray
    ref_px: np.ndarray
    homography: Optional[np.ndarray]
    inliers: np.ndarray
    features: int
    reason: str = ""

    @property
    def inlier_share(self) -> float:
        return float(self.inliers.mean()) if self.inliers.size else 0.0


def match_ground(ref: np.ndarray, cur: np.ndarray, k: np.ndarray, rot: np.ndarray, t_prior: np.ndarray, n: np.ndarray,
                 d: float, cfg: ImagePoseConfig) -> GroundMatches:
    """Corners on the current frame's ground tracked into the reference frame, and the dominant plane they fit.

    ``rot``, ``t_prior`` (reference camera frame), ``n`` (current camera frame) and ``d`` give the prior plane
    homography: the reference is warped into the current view by it, so what is left to track is a small shift
    with the ground's perspective change over a long baseline already undone. Raises cv2.error on degenerate
    input (the callers' per-frame paths catch it).
    """
    k_inv = np.linalg.inv(k)
    h_prior = k @ (rot + np.outer(t_prior, n) / d) @ k_inv          # pixels cur -> ref, from the prior
    none = np.zeros((0, 2), np.float32)
    pts = _ground_corners(cur, k_inv, n, d, cfg, _overlap_mask(h_prior, cur.shape, cfg.lk_window_px))
    if pts.shape[0] < cfg.min_inliers:
        return GroundMatches(none, none, None, np.zeros(0, bool), int(pts.shape[0]),
                             f"too few features on the ground ({pts.shape[0]} < {cfg.min_inliers})")
    h, w = cur.shape
    warped = cv2.warpPerspective(ref, h_prior, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                 borderMode=cv2.BORDER_CONSTANT)
    found, cur_pts = _track(cur, warped, pts, cfg)
    tracked = _apply(h_prior, found)
    n_feat = int(pts.shape[0])
    if tracked.shape[0] < cfg.min_inliers:
        return GroundMatches(cur_pts, tracked, None, np.zeros(tracked.shape[0], bool), n_feat,
                             f"too few features tracked ({tracked.shape[0]} of {n_feat})")
    hom, mask = cv2.findHomography(cur_pts, tracked, cv2.RANSAC, cfg.ransac_px, maxIters=500, confidence=0.995)
    if hom is None or mask is None:
        return GroundMatches(cur_pts, tracked, None, np.zeros(tracked.shape[0], bool), n_feat,
                             "degenerate: no homography fits the tracked features")
    inl = mask.reshape(-1).astype(bool)
    out = GroundMatches(cur_pts, tracked, hom, inl, n_feat)
    if int(inl.sum()) < cfg.min_inliers or out.inlier_share < cfg.min_inlier_share:
        return replace(out, reason=f"no dominant ground plane ({int(inl.sum())} of {tracked.shape[0]} inliers)")
    return out


def plane_prediction_sigma(xc: np.ndarray, rot: np.ndarray, t: np.ndarray, n: np.ndarray, d: float,
                           cov_t: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """1-σ error (normalised units) of the plane-predicted reference point along ``direction`` (2×N, any
    length), per current point ``xc`` (2×N normalised), from the covariance ``cov_t`` of t (reference camera).

    The prediction is π(R x + t n^T x / d); its Jacobian in t is (a / q_z) [[1, 0, -u], [0, 1, -v]] with
    a = n^T x / d, q = the predicted point, (u, v) = π(q). Along the parallax direction this is the error
    the pose adds to the measured height; directions the ground features constrained well add little.
    """
    xh = np.vstack([xc, np.ones((1, xc.shape[1]))])
    a = (n @ xh) / d
    q = (rot + np.outer(t, n) / d) @ xh
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = q[0] / q[2], q[1] / q[2]
        dn = direction / np.linalg.norm(direction, axis=0, keepdims=True)
        # J^T ĝ (3×N): the t-direction whose error moves the prediction along ĝ.
        jg = (a / q[2]) * np.vstack([dn[0], dn[1], -(u * dn[0] + v * dn[1])])
    var = np.einsum("in,ij,jn->n", jg, cov_t, jg)
    out: np.ndarray = np.sqrt(np.maximum(var, 0.0))
    return out


def widen_for_image_pose(sigma0: np.ndarray, xc: np.ndarray, xr: tuple[np.ndarray, np.ndarray],
                         pair: tuple[np.ndarray, np.ndarray, np.ndarray, float], gain: np.ndarray,
                         gnorm: np.ndarray, image_pose: ImagePose, detect_sigmas: float) -> np.ndarray:
    """A telemetry pair's height σ (H×W) widened for an image pose: its translation error moves the plane
    prediction along the parallax direction (plane_prediction_sigma), extra noise; its scale error ε (the height
    above ground) makes heights read low by up to ``detect_sigmas`` · ε. Never easier than a telemetry pose.
    ``xc`` (2×H×W) and ``xr`` the pair's normalised points, ``pair`` = (R, t, n, d) its plane geometry, ``gain`` and
    ``gnorm`` its range gain (parallax.range_gain) and parallax gradient norm per pixel."""
    rot, t, n, d = pair
    xr_flat = np.stack(xr).reshape(2, -1)
    g = t[:2, None] - xr_flat * t[2]
    pose_n = plane_prediction_sigma(xc.reshape(2, -1).astype(np.float64), rot, t, n, d, image_pose.cov_ref_m2,
                                    g).reshape(sigma0.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma_pose = gain * pose_n / gnorm
    margin = 1.0 / max(1e-3, 1.0 - detect_sigmas * image_pose.scale_sigma_rel)
    out: np.ndarray = np.hypot(sigma0, sigma_pose) * margin
    return out


def _overlap_mask(h_cur_to_ref: np.ndarray, shape: tuple[int, ...], margin_px: int) -> Optional[np.ndarray]:
    """uint8 mask of the current pixels the reference frame saw (per the prior), or None (all of them).

    Features outside the overlap cannot be tracked: with long baselines they would be most of the corners.
    """
    h, w = shape[:2]
    m = float(margin_px)
    corners = np.array([[m, m, 1.0], [w - 1 - m, m, 1.0], [w - 1 - m, h - 1 - m, 1.0], [m, h - 1 - m, 1.0]])
    back = corners @ np.linalg.inv(h_cur_to_ref).T
    if not np.all(back[:, 2] > 1e-9):
        return None                           # the reference's edges reach the horizon: keep every corner
    poly = np.round(back[:, :2] / back[:, 2:3]).clip(-4 * w, 4 * w).astype(np.int32)
    mask = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(mask, poly, 255)
    return mask


def _ground_corners(grey: np.ndarray, k_inv: np.ndarray, n: np.ndarray, d: float, cfg: ImagePoseConfig,
                    mask: Optional[np.ndarray] = None) -> np.ndarray:
    """Corners (N×2 float32 pixels) in ``mask`` whose rays meet the ground within ``max_range_m``."""
    c = cv2.goodFeaturesToTrack(grey, cfg.max_features, cfg.quality, cfg.min_distance_px, mask=mask, blockSize=7)
    if c is None:
        return np.zeros((0, 2), np.float32)
    pts = c.reshape(-1, 2).astype(np.float32)
    x = _normalised(k_inv, pts)
    nx = x @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        rng = np.where(nx > 1e-3, d / nx, np.inf) * np.linalg.norm(x, axis=1)
    out: np.ndarray = pts[rng <= cfg.max_range_m]
    return out


def _normalised(k_inv: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """N×2 pixels -> N×3 homogeneous normalised coordinates."""
    h = np.hstack([pts.astype(np.float64), np.ones((pts.shape[0], 1))])
    out: np.ndarray = h @ k_inv.T
    return out


def _plane_map(rot: np.ndarray, t: np.ndarray, n: np.ndarray, d: float, xc: np.ndarray) -> np.ndarray:
    out: np.ndarray = xc @ (rot + np.outer(t, n) / d).T
    return out


def _project(k: np.ndarray, x: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        p = x @ k.T
        out: np.ndarray = np.where(x[:, 2:3] > 1e-6, p[:, :2] / p[:, 2:3], np.nan).astype(np.float32)
    return out


def _apply(hom: np.ndarray, pts: np.ndarray) -> np.ndarray:
    if pts.shape[0] == 0:
        return pts
    out: np.ndarray = cv2.perspectiveTransform(pts.reshape(-1, 1, 2).astype(np.float64), hom).reshape(-1, 2)
    return out.astype(np.float32)


def _track(cur: np.ndarray, ref: np.ndarray, pts: np.ndarray, cfg: ImagePoseConfig) -> tuple[np.ndarray, np.ndarray]:
    """Pyramidal LK cur -> ref (same view up to a small shift), kept where the track back lands on its start."""
    if pts.shape[0] == 0:
        return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32)
    win = (cfg.lk_window_px, cfg.lk_window_px)
    term = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    p0 = pts.reshape(-1, 1, 2)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(cur, ref, p0, p0.copy(), winSize=win, maxLevel=cfg.lk_levels, criteria=term)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(ref, cur, p1, p0.copy(), winSize=win, maxLevel=cfg.lk_levels,
                                            criteria=term, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    h, w = cur.shape
    p1r, backr = p1.reshape(-1, 2), back.reshape(-1, 2)
    fb = np.linalg.norm(backr - pts, axis=1)
    inside = (p1r[:, 0] >= 0) & (p1r[:, 0] <= w - 1) & (p1r[:, 1] >= 0) & (p1r[:, 1] <= h - 1)
    keep = (st1.reshape(-1) == 1) & (st2.reshape(-1) == 1) & (fb <= cfg.max_fb_error_px) & inside
    return p1r[keep].astype(np.float32), pts[keep]


def _solve_t(xc: np.ndarray, xr: np.ndarray, rot: np.ndarray, n: np.ndarray, d: float, f: float, gate_px: float
             ) -> tuple[Optional[np.ndarray], np.ndarray, np.ndarray]:
    """Weighted least squares for t (reference camera frame) with R fixed: (t, residuals px, covariance m²).

    Each equation is divided by the predicted depth term so its residual is the reprojection error in
    normalised units; two reweightings, then matches beyond 3 × ``gate_px`` are dropped and t solved again.
    """
    y = xc @ rot.T
    a = (xc @ n) / d
    u, v = xr[:, 0] / xr[:, 2], xr[:, 1] / xr[:, 2]
    zeros = np.zeros_like(a)
    a_mat = np.concatenate([np.stack([a, zeros, -u * a], 1), np.stack([zeros, a, -v * a], 1)])
    b = np.concatenate([u * y[:, 2] - y[:, 0], v * y[:, 2] - y[:, 1]])
    t = np.zeros(3)
    keep = np.ones(b.size, bool)
    for it in range(4):
        denom = np.tile(y[:, 2] + a * t[2], 2)
        wgt = np.where(np.abs(denom) > 1e-6, 1.0 / np.abs(denom), 0.0) * keep
        aw, bw = a_mat * wgt[:, None], b * wgt
        if np.linalg.matrix_rank(aw) < 3:
            return None, np.full(xc.shape[0], np.inf), np.full((3, 3), np.inf)
        t, *_ = np.linalg.lstsq(aw, bw, rcond=None)
        res = (aw @ t - bw) * f
        if it == 2:
            keep = keep & (np.abs(res) <= 3 * gate_px)
    per_point = np.hypot(res[: xc.shape[0]], res[xc.shape[0]:])
    m = max(int(keep.sum()) - 3, 1)
    sigma_n2 = float(np.sum(res[keep] ** 2)) / m / (f * f)          # normalised residual variance
    cov = sigma_n2 * np.linalg.inv(aw.T @ aw)
    return t, per_point, cov
