"""Motion geometry: heights above the ground from the drone's own motion, independent of the network (ARCHITECTURE.md §11).

Between the current frame (c) and an earlier one (r) with known poses, points of the ground plane map by the
plane-induced homography; a point ``h`` above the plane is displaced from that prediction along the
epipolar direction. Frames: camera = OpenCV (x right, y down, z forward), world = local NED. The
plane-plus-parallax algebra (derivation, terrain fit, the overhang check) is in fusion.parallax.
Flow: the reference image is first warped by the plane homography into the current view, so the flow DIS
has to find is only the residual parallax (small for the ground even with tens of metres of baseline; the
plane is the ground's, or a roof's when the window looks at one: fusion.plane_sweep). The
height of the ground itself is the terrain (slopes of a few degrees read as metres at 100 m): a smooth
quadratic surface is fitted robustly to the heights and removed, so ``h`` is the height above the *local*
ground. Pure numpy/OpenCV, no I/O; memory is bounded in time (``history_s``) and count.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import replace
from typing import Deque, Optional

import cv2
import numpy as np

from edge_landing.runtime.core.camera import Intrinsics, Mount
from edge_landing.runtime.fusion.burst import FrameBurst
from edge_landing.runtime.fusion.chroma import ChromaMaker, chroma_unmatched
from edge_landing.runtime.fusion.image_checks import (
    along_epipolar_lines,
    moved_as_posed,
    predicted_motion_px,
    texture_masks,
)
from edge_landing.runtime.fusion.image_motion import ImagePose, widen_for_image_pose
from edge_landing.runtime.fusion.keyframes import (
    Keyframe,
    PairNoise,
    ground_window,
    pick_reference,
    prune_keyframes,
    store_keyframe,
    warp_window,
    window_ground,
)
from edge_landing.runtime.fusion.motion_config import (
    POSE_IMAGE,
    POSE_TELEMETRY,
    DisPreset,
    MotionConfig,
    ParallaxResult,
)
from edge_landing.runtime.fusion.odometry import ImageOdometry
from edge_landing.runtime.fusion.parallax import (
    CameraPose,
    column_seen,
    fit_ground,
    ground_surface,
    height_sigma,
    ned_points,
    parallax_height,
    plane_homography,
    range_gain,
    thin_factor,
)
from edge_landing.runtime.fusion.plane_sweep import sweep_plane
from edge_landing.runtime.fusion.residual import ray_footprints, unmatched_pixels, without_wide_regions
from edge_landing.runtime.fusion.rotation_fit import drift_beyond_an_ekf, pair_rotation_error, rotation_flow
from edge_landing.runtime.fusion.streaks import RainFilter

__all__ = ["POSE_IMAGE", "POSE_TELEMETRY", "CameraPose", "DisPreset", "MotionConfig", "MotionStage", "ParallaxResult",
           "parallax_height", "plane_homography"]


class MotionStage:
    """Keeps a bounded ring of grey keyframes with poses; ``update`` measures heights against the best one."""

    def __init__(self, config: MotionConfig, intrinsics: Intrinsics, mount: Mount):
        self.config = config
        self.mount = mount
        scale = min(1.0, config.max_width_px / intrinsics.width)
        w, h = max(32, int(round(intrinsics.width * scale))), max(32, int(round(intrinsics.height * scale)))
        self.size_hw = (h, w)
        self.intrinsics = intrinsics.scaled(w, h)
        i = self.intrinsics
        # OpenCV's warps and flows put pixel centres at integers; the runtime's rays at +0.5.
        self.k_cv = np.array([[i.fx, 0.0, i.cx - 0.5], [0.0, i.fy, i.cy - 0.5], [0.0, 0.0, 1.0]])
        self._k_inv = np.linalg.inv(self.k_cv)
        self._undistort = None
        if i.dist:   # the plane model is pinhole: undistort frames once into the same camera without distortion
            self._undistort = cv2.initUndistortRectifyMap(self.k_cv, np.asarray(i.dist, np.float64), None,
                                                          self.k_cv, (w, h), cv2.CV_16SC2)
        self._history: Deque[Keyframe] = deque()
        self._pair_noise = PairNoise()   # keyframes' failed pairs, with the ground each looked at
        self._dis = config.dis_preset.create()
        self._dis.setVariationalRefinementIterations(config.dis_refine_iterations)
        self._dis.setFinestScale(config.dis_finest_scale)
        self._dis.setPatchSize(config.dis_patch_px)
        self._dis.setPatchStride(config.dis_patch_stride_px)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        self._pix = (xx, yy)
        self._norm = np.stack([(xx - self.k_cv[0, 2]) / i.fx, (yy - self.k_cv[1, 2]) / i.fy])   # 2×H×W, normalised
        self.last: Optional[ParallaxResult] = None
        self.last_reason = ""
        self._ground: Optional[tuple[float, float]] = None   # (time, NED down of the local ground last measured)
        self._scan = 0                                         # next window position without a candidate spot
        self._rain = RainFilter(config.streaks)               # rain streaks out of each pair (fusion.streaks)
        self._burst = FrameBurst(config.burst, self.k_cv)      # three frames aligned on the ground (fusion.burst)
        self.position_ned_m: Optional[np.ndarray] = None  # where the last frame was placed (odometry or NED)
        self._odometry = ImageOdometry(config, self.k_cv)  # places frames without a telemetry position
        self._chroma = ChromaMaker(self.k_cv, i.dist, (h, w)) if config.residual.colour else None   # fusion.chroma

    @property
    def keyframes(self) -> tuple[Keyframe, ...]:
        """The keyframe ring, oldest first (the newest is the last frame ``update`` stored)."""
        return tuple(self._history)

    @property
    def image_pose(self) -> Optional[ImagePose]:
        """This frame's image-only estimate (None: it had a telemetry position)."""
        return self._odometry.estimate

    @property
    def odometry_epoch(self) -> int:
        """+ 1 each time image odometry starts a new frame of its own."""
        return self._odometry.epoch

    @property
    def anchored(self) -> bool:
        """Image positions chained from a telemetry position less than ``history_s`` ago (the telemetry's frame)."""
        return self._odometry.anchored

    @property
    def ground_down_m(self) -> Optional[float]:
        """NED down of the local ground last measured (None: not yet; the rangefinder's plane is used)."""
        return None if self._ground is None else self._ground[1]

    def reset(self) -> None:
        self._history.clear()
        self._pair_noise.clear()
        self.last, self.last_reason = None, ""
        self._ground = None
        self._rain.reset()
        self._burst.reset()
        self.position_ned_m = None
        self._odometry.reset()

    def _plane_pose(self, pose: CameraPose, time_s: float) -> CameraPose:
        """The pose with the plane at the ground last measured near the spot, when recent and lower.

        A rangefinder reads the first surface below the vehicle (a roof when flying over a house): a plane
        there, tens of metres above the ground the camera looks at, leaves the ground with a parallax the
        flow cannot follow. The ground's level in NED, measured from the last frame pair, stays valid while
        the vehicle moves; heights do not depend on the plane chosen (the plane only has to be close).
        """
        if self._ground is None or not 0.0 <= time_s - self._ground[0] <= self.config.history_s:
            return pose
        d = self._ground[1] - float(pose.position_ned_m[2])
        # Only lower than the rangefinder's surface: a window centred on a roof fits the roof as its "local
        # ground", which must not lift the plane for the street views that follow.
        if not d > pose.agl_m:
            return pose
        return CameraPose(pose.r_nc, pose.position_ned_m, d)

    def grey(self, image: np.ndarray) -> np.ndarray:
        """RGB (or grey) uint8 image at any size -> grey uint8 at the stage's size, undistorted."""
        g = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        h, w = self.size_hw
        if g.shape != (h, w):
            g = cv2.resize(g, (w, h), interpolation=cv2.INTER_AREA)
        if g.dtype != np.uint8:
            g = np.clip(g, 0, 255).astype(np.uint8)
        if self._undistort is not None:
            g = cv2.remap(g, self._undistort[0], self._undistort[1], cv2.INTER_LINEAR)
        return g

    def update(self, image: np.ndarray, pose: CameraPose, time_s: float,
               focus_ned_m: Optional[np.ndarray] = None) -> Optional[ParallaxResult]:
        """Add a frame; returns its height evidence, or None (``last_reason`` says why).

        ``focus_ned_m``: a candidate spot (local NED, 3) or several (K×3, the first preferred); when the ground
        band is larger than ``window_hw`` the window is centred on the one a keyframe sees best (else it scans).
        """
        cfg = self.config
        self.last, self.position_ned_m = None, None
        if not (math.isfinite(pose.agl_m) and pose.agl_m >= cfg.min_agl_m):
            self.last_reason = f"height above ground {pose.agl_m} m unusable (need >= {cfg.min_agl_m} m)"
            return None
        raw = self.grey(image)
        # Rain and sensor noise out (fusion.burst), aligned on the ground the pairs are measured against.
        grey = self._burst.clean(raw, self._plane_pose(pose, time_s), time_s)
        chroma = None if self._chroma is None else self._chroma(image)     # half-size Cr, Cb (fusion.chroma)
        prune_keyframes(self._history, time_s, cfg.history_s)
        source = POSE_TELEMETRY if np.all(np.isfinite(pose.position_ned_m)) else POSE_IMAGE
        self._odometry.estimate, self.last_reason, restarted = None, "", None
        if source == POSE_IMAGE:
            pose, restarted = self._odometry.chain(grey, pose, time_s, self._history[-1] if self._history else None)
            if restarted is not None:      # a new odometry frame: the keyframes and the ground are in the old one
                self._history.clear()
                self._ground = None
        else:
            self._odometry.telemetry_seen(time_s)
            if any(s.source == POSE_IMAGE for s in self._history):
                self._history.clear()      # odometry positions are not in the telemetry's frame
                self._ground = None
        if not self._history:
            self._pair_noise.clear()
        raw_agl = pose.agl_m    # the metric scale: the measured height (carried, when refused), not the plane's
        pose = self._plane_pose(pose, time_s)
        result = None
        window, ref = self._choose_window(pose, focus_ned_m, time_s)
        if window is None:
            self.last_reason = f"no ground within {cfg.max_range_m:.0f} m in view"
        elif ref is not None and source == POSE_IMAGE:
            located, est = self._odometry.locate(grey, replace(pose, agl_m=raw_agl), ref)   # the pair, directly
            pose = replace(pose, position_ned_m=located.position_ned_m)
            if est.ok:
                result = self._measure(grey, chroma, pose, ref, time_s, window, est, raw)
            else:
                self.last_reason = est.describe()
        elif ref is not None and not self._moved_as_posed(raw, pose, window):
            # Not stored either: a frozen image with a new pose would mislead the pairs that follow.
            self.last_reason = ("the images did not move as the vehicle did (a frozen camera feed, or telemetry "
                                "that does not belong to these frames)")
            return None
        elif ref is not None:
            result = self._measure(grey, chroma, pose, ref, time_s, window, raw=raw)
        self.position_ned_m = pose.position_ned_m.copy()
        # An anchored image position is in the telemetry's frame: a position dropout, not a new frame.
        store_keyframe(self._history, Keyframe(time_s, grey, pose, POSE_TELEMETRY if self.anchored else source,
                                               raw_agl, chroma), cfg)
        if restarted and window is not None:     # (the ring is empty: "no earlier frame yet" says less)
            self.last_reason = f"odometry started over: {restarted}"
        self.last = result
        return result

    def _moved_as_posed(self, grey: np.ndarray, pose: CameraPose, window: tuple[slice, slice]) -> bool:
        """Whether the window moved against the newest keyframe as the telemetry poses say (image_checks): a
        frozen feed paired with an older, real keyframe gives a consistent flow read with the wrong pose, and
        its evidence placed metres away."""
        newest = self._history[-1]
        # The frames as the camera gave them: medians (fusion.burst) of a frozen feed under moving poses differ.
        before = self._burst.raw_at(newest.time_s)
        before = newest.grey if before is None else before
        rs, cs = window
        hom = plane_homography(self.k_cv, pose, newest.pose)[0]
        return moved_as_posed(np.ascontiguousarray(grey[rs, cs]), before[rs, cs], warp_window(before, hom, window),
                              predicted_motion_px(hom, rs, cs), self.config.checks)

    def _choose_window(self, pose: CameraPose, focus: Optional[np.ndarray], time_s: float
                       ) -> tuple[Optional[tuple[slice, slice]], Optional[Keyframe]]:
        """The window and keyframe for this frame: among the candidate spots, the one whose best keyframe detects
        the smallest height (the first unless another is ``focus_preference`` times better). The network's spot
        often lies where the vehicle is flying to, near the epipole, where no baseline gives parallax: a
        window there measures nothing a confirmation can use, while other landable ground would confirm."""
        foci: list[Optional[np.ndarray]] = [None] if focus is None else list(np.atleast_2d(focus))
        best: tuple[Optional[tuple[slice, slice]], Optional[Keyframe]] = (None, None)
        best_det, reason = math.inf, ""
        for k, spot in enumerate(foci):
            window = self._window(pose, spot)
            if window is None:
                continue
            ref, det = self._pick_reference(pose, window, time_s)
            if best[0] is None:
                best, reason = (window, ref), self.last_reason
            score = det / self.config.focus_preference if k == 0 else det
            if ref is not None and score < best_det:
                best, best_det, reason = (window, ref), score, ""
        self.last_reason = reason
        return best

    def _window(self, pose: CameraPose, focus: Optional[np.ndarray]) -> Optional[tuple[slice, slice]]:
        """Rows and columns DIS runs on (keyframes.ground_window); without a candidate spot, the scan moves on."""
        window = ground_window(pose, focus, self._norm, self.size_hw, self.k_cv, self.config, self._scan)
        if focus is None and window is not None:
            self._scan = (self._scan + 1) % 6
        return window

    def _pick_reference(self, pose: CameraPose, window: tuple[slice, slice], time_s: float
                        ) -> tuple[Optional[Keyframe], float]:
        """keyframes.pick_reference on the ring for a frame at ``time_s``; sets ``last_reason`` when there is none."""
        failed = self._pair_noise.penalised(time_s, window_ground(pose, window, self._k_inv), self.config)
        ref, det, reason = pick_reference(self._history, pose, window, self.k_cv, self._k_inv, self.size_hw,
                                          self.config, failed)
        if ref is None:
            self.last_reason = reason
        return ref, det

    def _measure(self, grey: np.ndarray, chroma: Optional[np.ndarray], pose: CameraPose, ref: Keyframe, time_s: float,
                 window: tuple[slice, slice], image_pose: Optional[ImagePose] = None,
                 raw: Optional[np.ndarray] = None) -> Optional[ParallaxResult]:
        """One pair's evidence on ``window``. ``raw``: this frame as the camera gave it, when ``grey`` is the median of
        three (fusion.burst): the rain the median took out counts as rain found."""
        cfg = self.config
        rs, cs = window
        looked_at = window_ground(pose, window, self._k_inv)      # before a roof's plane replaces the ground's
        # A window on a roof is measured against the roof's plane, found from the images (fusion.plane_sweep).
        sweep = sweep_plane(self.k_cv, pose, ref.pose, ref.grey, grey[rs, cs], (rs.start, cs.start), cfg.sweep)
        if sweep.raised:
            pose = replace(pose, agl_m=sweep.level_m)
        hom, rot, t, n, d = plane_homography(self.k_cv, pose, ref.pose)
        wrp = warp_window(ref.grey, hom, window)
        cur = np.ascontiguousarray(grey[rs, cs])
        # No texture, or images that did not move as the poses did, would read as level ground (image_checks).
        tex, beyond_noise = texture_masks(cur, cfg.checks)
        if tex.mean() < cfg.checks.min_textured_share:
            self.last_reason = (f"too little texture to measure ({100 * tex.mean():.0f} % of the window): a blank, "
                                f"dark or saturated image")
            return None
        raw_cur = None if raw is None or raw is grey else np.ascontiguousarray(raw[rs, cs])
        cur, wrp, rain = self._rain.apply(cur, wrp, time_s, raw_cur)
        if rain > 0:   # streaks count as texture and as noise alike: the check is made again without them
            beyond_noise = texture_masks(cur, cfg.checks)[1]
        flow = np.asarray(self._dis.calc(cur, wrp, None))  # type: ignore[call-overload]
        xx, yy = self._pix[0][rs, cs], self._pix[1][rs, cs]
        mx, my = xx + flow[..., 0], yy + flow[..., 1]
        to_ref = (mx - cs.start, my - rs.start)          # where each window pixel's match lies in the warped window
        matched = cv2.remap(wrp, *to_ref, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        photo_ok = np.abs(cur.astype(np.int16) - matched.astype(np.int16)) <= cfg.max_photometric_error
        # Where the matched point lies in the reference image (pixel-centre convention), then normalised.
        qx = hom[0, 0] * mx + hom[0, 1] * my + hom[0, 2]
        qy = hom[1, 0] * mx + hom[1, 1] * my + hom[1, 2]
        qz = hom[2, 0] * mx + hom[2, 1] * my + hom[2, 2]
        ur, vr = qx / qz, qy / qz
        h, w = self.size_hw
        in_ref = (qz > 0) & (ur >= 0) & (ur <= w - 1) & (vr >= 0) & (vr <= h - 1)
        k_inv = self._k_inv
        # Normalised coordinates, H×W per component (2×H×W for the current frame's pixels).
        xr = ((ur - self.k_cv[0, 2]) * k_inv[0, 0], (vr - self.k_cv[1, 2]) * k_inv[1, 1])
        xc = self._norm[:, rs, cs]
        # The telemetry's rotation drift between the pair, measured across the epipolar lines (rotation_fit).
        f = 0.5 * (self.intrinsics.fx + self.intrinsics.fy)
        omega = pair_rotation_error(xc, xr, rot, t, n, d, in_ref & tex & photo_ok, f, cfg.rotation_fit)
        if np.any(omega != 0.0):
            drift_deg = drift_beyond_an_ekf(omega, time_s - ref.time_s, cfg.rotation_fit)
            if drift_deg:
                self.last_reason = (f"the autopilot's attitude moved {drift_deg:.2f}° in {time_s - ref.time_s:.1f} s "
                                    f"against the images, more than an estimator drifts")
                return None
            dx, dy = rotation_flow(xr[0], xr[1], omega)
            xr = (xr[0] - dx, xr[1] - dy)
        hgt, gnorm, cross = parallax_height(xc, xr, rot, t, n, d)
        # The residual across the epipolar direction is flow error only (parallax lies along it): its robust
        # spread is this pair's flow noise, used when above the configured floor.
        # Textureless pixels are left out: their flow is filled in from around them, with no residual of its own.
        matched_ok = in_ref & np.isfinite(hgt) & photo_ok
        noise_px = cfg.flow_noise_px
        spread = cross[matched_ok & tex]
        if spread.size >= 100:
            noise_px = max(noise_px, 1.4826 * float(np.median(spread)) * f)
        self._pair_noise.remember(self._history, ref.time_s, time_s, noise_px, looked_at, cfg)
        explained = matched_ok & (cross * f <= max(cfg.max_cross_parallax_px, 3 * noise_px))
        # NED point of each pixel at its measured height (the plane point where the flow is not trusted). The
        # height may be negative (ground below the plane: the point is farther along its ray than the plane's).
        lam_scale = np.where(explained, np.clip(1.0 - np.where(explained, hgt, 0.0) / d, 0.05, 20.0), 1.0)
        ned, nx = ned_points(pose, xc, lam_scale)
        near = (nx > 0) & (np.hypot(ned[0] - pose.position_ned_m[0], ned[1] - pose.position_ned_m[1])
                           <= cfg.max_range_m)
        reliable = near & explained
        with np.errstate(divide="ignore", invalid="ignore"):
            sigma_plane = d * (noise_px / f) / gnorm
        fit = fit_ground(ned, hgt, sigma_plane, reliable & (sigma_plane <= cfg.max_sigma_h_m), pose.position_ned_m,
                         start_m=0.0 if sweep.raised else None)
        ground = ground_surface(fit, ned, pose.position_ned_m)
        local = hgt - ground
        gain = range_gain(d, ground)
        sigma0, widened, usable = height_sigma(gain, noise_px / f, gnorm, local, reliable)
        noise_px *= widened          # (× 1.0 when the heights' spread did not widen it)
        if image_pose is not None:
            sigma0 = widen_for_image_pose(sigma0, xc, xr, (rot, t, n, d), gain, gnorm, image_pose, cfg.detect_sigmas)
        height = np.where(reliable, local, np.nan).astype(np.float32)
        patch_px = float(self._dis.getPatchSize() * 2 ** cfg.dis_finest_scale)   # its footprint on the ground:
        footprint = patch_px * np.sqrt(np.sum((ned - pose.position_ned_m[:, None, None]) ** 2, axis=0)) / f
        # A textureless pixel, or one whose texture is only the sensor's noise (murky water), like one whose
        # patch is too large, may report an obstacle but not confirm: its flow is its neighbours' (a smooth
        # wall's face still reads partly high; a blank image or a pond next to its bank reads level).
        resolved = (footprint <= cfg.max_patch_footprint_m) & tex & beyond_noise
        # An edge along the epipolar lines slides along itself: its parallax is not seen (image_checks).
        with np.errstate(invalid="ignore"):
            standing = reliable & (np.abs(local) >= cfg.checks.outline_min_m) & (np.abs(local) >= cfg.detect_sigmas * sigma0)
        resolved &= ~along_epipolar_lines(cur, self.k_cv @ (-rot.T @ t), (cs.start, rs.start), cfg.checks, wrp,
                                          standing)
        if sweep.verified is not None:   # on a roof's plane, only what matches that plane confirms
            resolved &= sweep.verified
        if cfg.overhang_check_m > 0:   # ground seen under a crown or eaves cannot confirm
            resolved &= column_seen(pose, self.k_cv, (cs.start, rs.start), xc, ned, reliable,
                                    cfg.overhang_check_m)
        detectable = np.where(reliable & resolved, cfg.detect_sigmas * sigma0, np.inf).astype(np.float32)
        out_ned = np.where(near[None], ned, np.nan).astype(np.float32)
        odd = unmatched_pixels(cur, matched, matched_ok & tex, near & in_ref, cfg.residual, rain, flow_noise_px=noise_px)
        if ref.chroma is not None and chroma is not None:
            odd |= chroma_unmatched(chroma, ref.chroma, hom, window, to_ref, matched_ok & tex, near & in_ref,
                                    cfg.residual, rain, noise_px)
        odd = without_wide_regions(odd, pose, self.k_cv, (cs.start, rs.start), cfg.residual)
        unmatched = ray_footprints(pose, xc[:, odd], np.nan_to_num(ground[odd]), cfg.residual)
        baseline = float(np.linalg.norm(pose.position_ned_m - ref.pose.position_ned_m))
        self.last_reason = ""
        # Only a pair whose flow held (noise near the floor, most of the window explained) may move the plane:
        # a failed pair's fit is noise, and a plane set from it would spoil the next pairs too.
        if not sweep.raised and np.any(fit != 0.0) and noise_px <= cfg.max_plane_noise_px and usable.mean() >= 0.5:
            self._ground = (time_s, float(pose.position_ned_m[2] + d - np.median(ground[usable])))
        return ParallaxResult(time_s, rs, cs, height, sigma0.astype(np.float32), detectable, out_ned, baseline,
                              time_s - ref.time_s, fit, noise_px, near & in_ref & np.isfinite(hgt) & ~explained,
                              POSE_TELEMETRY if image_pose is None else POSE_IMAGE,
                              0.0 if image_pose is None else image_pose.sigma_m, rain,
                              sweep.ground_m - sweep.level_m, unmatched, thin_factor(footprint, cfg.thin_obstacle_m))
