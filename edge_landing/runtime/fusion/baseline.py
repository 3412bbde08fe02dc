"""Which earlier frame to pair with: the smallest height each keyframe could detect (ARCHITECTURE.md §11).

Pure numpy, no I/O. Frames: camera = OpenCV (x right, y down, z forward), world = local NED.
"""
from __future__ import annotations

import math

import numpy as np

from edge_landing.runtime.fusion.motion_config import MotionConfig
from edge_landing.runtime.fusion.parallax import CameraPose, row_nanmedian


def window_probes(window: tuple[slice, slice]) -> np.ndarray:
    """A 5×4 grid of pixels (2×20, u then v) spread over the window, away from its top and left rims."""
    rs, cs = window
    uu, vv = np.meshgrid(np.linspace(cs.start + 0.1 * (cs.stop - cs.start), cs.stop - 1, 5),
                         np.linspace(rs.start + 0.1 * (rs.stop - rs.start), rs.stop - 1, 4))
    return np.vstack([uu.ravel(), vv.ravel()])


def detectable_heights_m(pose: CameraPose, refs: list[CameraPose], probes: np.ndarray, k_cv: np.ndarray,
                         k_inv: np.ndarray, size_hw: tuple[int, int], config: MotionConfig) -> np.ndarray:
    """For each reference pose, the smallest height above the ground plane it could detect at the probes.

    Median over the probes the reference still sees; inf where it sees too few of them (``min_overlap``), where
    the baseline is zero (hovering) or longer than ``max_baseline_ratio`` × the range to the ground.
    """
    h, w = size_hw
    xc = k_inv @ np.vstack([probes, np.ones(probes.shape[1])])
    r_ref = np.stack([p.r_nc for p in refs])                                 # M×3×3 NED <- ref camera
    p_ref = np.stack([p.position_ned_m for p in refs])                       # M×3
    rot = np.einsum("mji,jk->mik", r_ref, pose.r_nc)                         # R_r^T R_c
    t = np.einsum("mji,mj->mi", r_ref, pose.position_ned_m[None] - p_ref)    # R_r^T (p_c - p_r)
    n = pose.r_nc.T @ np.array([0.0, 0.0, 1.0])
    d = pose.agl_m
    q = np.einsum("mij,jk->mik", rot + t[:, :, None] * n[None, None, :] / d, xc)   # M×3×K, H_e x_c
    nx = n @ xc                                                              # K
    f = 0.5 * (k_cv[0, 0] + k_cv[1, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        xr = q[:, :2] / q[:, 2:3]
        ur = k_cv[0, 0] * xr[:, 0] + k_cv[0, 2]
        vr = k_cv[1, 1] * xr[:, 1] + k_cv[1, 2]
        inside = (q[:, 2] > 0) & (nx > 0)[None] & (ur >= 8) & (ur <= w - 9) & (vr >= 8) & (vr <= h - 9)
        z0 = d / nx[None] * q[:, 2]
        g = (t[:, :2, None] - xr * t[:, 2:3, None]) / z0[:, None]
        gnorm = np.where(inside, np.hypot(g[:, 0], g[:, 1]), np.nan)
        det = config.detect_sigmas * d * (config.flow_noise_px / f) / row_nanmedian(
            np.where(inside.any(axis=1, keepdims=True), gnorm, 0.0))
        # The noise-floor model above favours the longest baseline, but past about half the range to the ground
        # the two views differ too much (anything off the plane, occlusions) and the flow fails: the measured
        # noise grows several-fold and so does the detectable height (docs/ARCHITECTURE.md §11).
        rng = float(row_nanmedian((np.where(nx > 0, d / nx, np.nan) * np.sqrt(1.0 + xc[0] ** 2 + xc[1] ** 2))[None])[0])
    short = np.linalg.norm(t, axis=1) <= config.max_baseline_ratio * rng if math.isfinite(rng) else True
    return np.asarray(np.where((inside.mean(axis=1) >= config.min_overlap) & np.isfinite(det) & short, det, np.inf))
