"""The telemetry's relative-rotation error between a frame pair, measured from the flow (ARCHITECTURE.md §11).

An autopilot's attitude drifts against the truth by a few hundredths of a degree per second (a residual gyro
bias), so between frames seconds apart the relative rotation is off by about 0.1°: about a pixel at 640 px
across, several times the flow's own noise. Read as parallax, that pixel inflates the pair's noise estimate
(measured across the epipolar lines) until nothing can be confirmed, and tilts the heights.

A rotation error moves every image point by the same small-rotation field, whatever its depth, while
parallax moves points only *along* their epipolar lines. So the residual *across* the epipolar lines is
flow error plus rotation error, never parallax: fitting the rotation to it cannot absorb an obstacle. A ridge
keeps the directions the window cannot observe (usually the rotation whose flow runs along the epipolar
lines) at zero; their along-line residual is a smooth height offset that the terrain fit removes. Frames:
normalised image coordinates of the reference camera (OpenCV, x right, y down). Pure numpy.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from edge_landing.runtime.fusion.parallax import plane_residuals


@dataclass(frozen=True)
class RotationFitConfig:
    enabled: bool = True
    max_rad: float = 0.01          # larger fitted corrections (0.57°) are not a drift: the pair is left as it is
    stride_px: int = 3             # every this many pixels each way are used for the fit
    min_points: int = 200
    ridge: float = 0.01            # × the number of points: keeps unobservable rotations at zero
    # Points whose cross residual exceeds this are not fitted: a drift moves points by a pixel or two, while
    # flow that failed (a roof's tens of pixels of parallax smoothed by DIS) is off by more, in a pattern a
    # rotation would partly absorb and then spread over the whole window.
    max_residual_px: float = 4.0
    # Applied only when it explains the cross residual: its median must shrink to this share. With exact poses
    # the residual is flow noise, which three angles cannot explain, and the pair is measured as before.
    min_gain: float = 0.8
    # A fitted rotation larger than drift_floor_deg + max_drift_deg_s × the pair's time apart says the
    # autopilot's attitude drifts faster than an EKF's (a few hundredths of a degree per second), so it may be
    # off by degrees: a pixel's ray then meets the ground metres from where it is placed (1.5° at 60 m: 1.6 m,
    # more along the line of sight). That pair gives no evidence (distrusting the next pairs for 10 s as well
    # halved the targets under typical errors, docs/MEASUREMENTS.md). The floor is the fit's own noise, which
    # pairs a fraction of a second apart would otherwise read as a fast drift.
    max_drift_deg_s: float = 0.1
    drift_floor_deg: float = 0.05


def drift_beyond_an_ekf(omega: np.ndarray, apart_s: float, config: RotationFitConfig) -> float:
    """The fitted rotation in degrees when it is more than an EKF drifts in ``apart_s`` seconds, else 0."""
    angle_deg = math.degrees(float(np.linalg.norm(omega)))
    return angle_deg if angle_deg > config.drift_floor_deg + config.max_drift_deg_s * max(apart_s, 0.0) else 0.0


def rotation_flow(x: np.ndarray, y: np.ndarray, omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Displacement of normalised points (x, y) under a small camera rotation ``omega`` (radians, 3)."""
    wx, wy, wz = (float(v) for v in omega)
    return x * y * wx - (1.0 + x * x) * wy + y * wz, (1.0 + y * y) * wx - x * y * wy - x * wz


def pair_rotation_error(xc: np.ndarray, xr: tuple[np.ndarray, np.ndarray], rot: np.ndarray, t: np.ndarray,
                        n: np.ndarray, d: float, use: np.ndarray, focal_px: float,
                        config: RotationFitConfig = RotationFitConfig()) -> np.ndarray:
    """The relative-rotation error (radians, 3) of a pair measured against the plane's homography (the
    arguments of parallax.parallax_height: ``xc`` 2×H×W, ``xr`` two H×W arrays), from every ``stride_px``-th
    pixel where ``use`` (H×W) holds; zeros when disabled or when :func:`fit_rotation` finds none.
    ``focal_px`` converts the pixel bounds to normalised units."""
    if not config.enabled:
        return np.zeros(3)
    sel = (slice(None, None, config.stride_px), slice(None, None, config.stride_px))
    x_r = (xr[0][sel], xr[1][sel])
    _, z0, gx, gy, rx, ry = plane_residuals((xc[0][sel], xc[1][sel]), x_r, rot, t, n, d)
    return fit_rotation(x_r, rx, ry, gx, gy, use[sel] & (z0 > 0), config, max_residual=config.max_residual_px / focal_px)


def fit_rotation(xr: tuple[np.ndarray, np.ndarray], rx: np.ndarray, ry: np.ndarray, gx: np.ndarray,
                 gy: np.ndarray, use: np.ndarray, config: RotationFitConfig = RotationFitConfig(),
                 max_residual: float = np.inf) -> np.ndarray:
    """The small rotation (radians, 3) whose flow best explains the residuals (rx, ry) across the epipolar
    directions (gx, gy) at the points ``xr`` where ``use`` holds and the cross residual is at most
    ``max_residual``; zeros when there are too few points, the fit is larger than ``max_rad`` or explains too
    little (``min_gain``). Inputs of one shape (normalised units)."""
    zero = np.zeros(3)
    with np.errstate(invalid="ignore"):
        ok = use & np.isfinite(rx) & np.isfinite(ry) & (gx * gx + gy * gy > 0)
    if int(ok.sum()) < config.min_points:
        return zero
    x, y = xr[0][ok], xr[1][ok]
    g = np.hypot(gx[ok], gy[ok])
    ex, ey = gy[ok] / g, -gx[ok] / g                            # unit vector across the epipolar line
    c = rx[ok] * ex + ry[ok] * ey                               # the residual across it
    small = np.abs(c) <= max_residual
    if int(small.sum()) < config.min_points:
        return zero
    x, y, ex, ey, c = x[small], y[small], ex[small], ey[small], c[small]
    cols = [rotation_flow(x, y, unit) for unit in np.eye(3)]
    a = np.stack([fx * ex + fy * ey for fx, fy in cols], axis=1)
    keep = np.ones(c.size, bool)
    omega, res = zero, c
    for _ in range(2):   # a least-squares fit, then again without the points it leaves far out (occlusions)
        ak, ck = a[keep], c[keep]
        if ck.size < config.min_points:
            return zero
        omega = np.linalg.solve(ak.T @ ak + config.ridge * ck.size * np.eye(3), ak.T @ ck)
        res = c - a @ omega
        keep = np.abs(res) <= 3.0 * 1.4826 * float(np.median(np.abs(res))) + 1e-12
    if not np.all(np.isfinite(omega)) or float(np.max(np.abs(omega))) > config.max_rad:
        return zero
    if float(np.median(np.abs(res[keep]))) > config.min_gain * float(np.median(np.abs(c[keep]))):
        return zero   # res is c - a @ omega, and keep was chosen from it
    return omega
