"""Plane-plus-parallax algebra for motion geometry (ARCHITECTURE.md §11): pure numpy, no state, no I/O.

Frames: camera = OpenCV (x right, y down, z forward), world = local NED.

Derivation (normalised image coordinates, camera c = "1", camera r = "2"):
  X_r = R X_c + t with R = R_r^T R_c, t = R_r^T (p_c - p_r) (R_x: NED <- camera, p_x: camera position).
  Ground plane in camera c: n^T X = d, n = R_c^T (0, 0, 1) (world down in camera c), d = height above it.
  A point at height h above the plane: n^T X_c = d - h. With H_e = R + t n^T / d:
      X_r = H_e X_c + t h / d.
  Writing X_c = λ x_c (x_c = (x, y, 1), λ = (d - h) / n^T x_c) and Z0 = the reference-frame depth of the
  *plane* point on the same ray (h = 0), the projections differ exactly by
      x_r - π(H_e x_c) = h / (d - h) · (t_xy - x_r t_z) / Z0 = s · g,
  so s = r·g / |g|² and h = d s / (1 + s). ``g`` is the parallax a point would show per unit of h/(d-h):
  |g| ≈ |t⊥| / Z0, the baseline across the line of sight over the range. With flow noise σ pixels
  (σ_n = σ / f normalised), h has σ_h = (d - h)² / d · σ_n / |g| (dh/ds), d σ_n / |g| on the plane; the
  smallest height this pair could have detected is ``detect_sigmas`` · σ_h.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Union

import numpy as np

from edge_landing.runtime.core.camera import Attitude, Mount, ned_from_camera

# Normalised image coordinates: a 2×... array, or its two components (x, y) as separate arrays.
Coords = Union[np.ndarray, tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class CameraPose:
    """Camera pose at capture: NED <- camera rotation, camera position (NED, m), height above the ground (m)."""

    r_nc: np.ndarray
    position_ned_m: np.ndarray
    agl_m: float

    @staticmethod
    def of(mount: Mount, attitude: Attitude, position_ned_m: np.ndarray, agl_m: float) -> CameraPose:
        return CameraPose(ned_from_camera(mount, attitude), np.asarray(position_ned_m, np.float64).reshape(3),
                          float(agl_m))


def plane_homography(k: np.ndarray, cur: CameraPose, ref: CameraPose) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                               np.ndarray, float]:
    """(H pixel c -> r, R, t, n, d): the ground plane's homography between current and reference frames.

    ``k`` is the 3×3 intrinsic matrix in OpenCV's pixel-centre convention. The plane is horizontal at
    the current frame's height above ground below the current camera.
    """
    rot = ref.r_nc.T @ cur.r_nc
    t = ref.r_nc.T @ (cur.position_ned_m - ref.position_ned_m)
    n = cur.r_nc.T @ np.array([0.0, 0.0, 1.0])
    d = cur.agl_m
    h_norm = rot + np.outer(t, n) / d
    return k @ h_norm @ np.linalg.inv(k), rot, t, n, d


def parallax_height(x_c: Coords, x_r: Coords, rot: np.ndarray, t: np.ndarray, n: np.ndarray, d: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Heights above the plane from matched normalised points (2×... each): (h, |g|, cross-epipolar residual).

    ``x_r`` is where the current frame's point ``x_c`` was found in the reference frame. See the module
    docstring for the derivation: r = x_r - π(H_e x_c) = s·g, h = d·s/(1+s). Any trailing shape (2×N, 2×H×W);
    float32 inputs are computed in float64. Written per component: a 3×3 product over tens of thousands of
    points costs several times more as matrix products with stacked homogeneous coordinates.
    """
    nx, z0, gx, gy, rx, ry = plane_residuals(x_c, x_r, rot, t, n, d)
    with np.errstate(invalid="ignore", divide="ignore"):
        g2 = gx * gx + gy * gy
        s = (rx * gx + ry * gy) / g2
        gnorm = np.sqrt(g2)
        cross = np.abs(rx * gy - ry * gx) / gnorm
        h = d * s / (1.0 + s)
    bad = ~(nx > 0) | ~(z0 > 0) | ~(g2 > 0)
    h[bad] = np.nan
    gnorm[bad] = 0.0
    return h, gnorm, cross


def plane_residuals(x_c: Coords, x_r: Coords, rot: np.ndarray, t: np.ndarray, n: np.ndarray, d: float
                    ) -> tuple[np.ndarray, ...]:
    """(n^T x_c, Z0, g_x, g_y, r_x, r_y) per point: the plane terms of :func:`parallax_height` (its docstring:
    r = x_r - π(H_e x_c) is the residual, g the parallax direction per unit of h/(d-h))."""
    x, y = np.asarray(x_c[0], np.float64), np.asarray(x_c[1], np.float64)
    xr, yr = np.asarray(x_r[0], np.float64), np.asarray(x_r[1], np.float64)
    he = rot + np.outer(t, n) / d
    nx = n[0] * x + n[1] * y + n[2]                           # > 0: the ray meets the plane ahead
    q = [he[i, 0] * x + he[i, 1] * y + he[i, 2] for i in range(3)]   # H_e x_c (homogeneous, reference frame)
    with np.errstate(invalid="ignore", divide="ignore"):
        z0 = d / nx * q[2]                                    # reference depth of the plane point on this ray
        gx, gy = (t[0] - xr * t[2]) / z0, (t[1] - yr * t[2]) / z0
        rx, ry = xr - q[0] / q[2], yr - q[1] / q[2]
    return nx, z0, gx, gy, rx, ry


def ned_points(pose: CameraPose, xc: np.ndarray, lam_scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """NED points (3×...) of normalised pixels ``xc`` (2×..., e.g. 2×N or 2×H×W) on the plane ``agl_m`` below, their
    ray depths scaled by ``lam_scale`` (shaped as one component of ``xc``), and n^T x per pixel (> 0: the ray
    meets the plane ahead)."""
    n = pose.r_nc.T @ np.array([0.0, 0.0, 1.0])
    nx = n[0] * xc[0] + n[1] * xc[1] + n[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.where(nx > 0, pose.agl_m / nx, np.nan) * lam_scale
    r = pose.r_nc
    pts = np.empty((3,) + tuple(xc.shape[1:]), np.float64)
    for i in range(3):
        pts[i] = (r[i, 0] * xc[0] + r[i, 1] * xc[1] + r[i, 2]) * lam + pose.position_ned_m[i]
    return pts, nx


def range_gain(d: float, ground: np.ndarray) -> np.ndarray:
    """dh/ds = (d - h)^2 / d per pixel, for the local ground ``ground`` above the plane ``d`` below the camera: the
    plane's sensitivity holds only at the plane; ground below it (a rangefinder reading a roof, a slope) is
    measured with the error of its own, larger, range (h is taken as at most 0.9 d)."""
    out: np.ndarray = np.maximum(d - ground, 0.1 * d) ** 2 / d
    return out


def height_sigma(gain: np.ndarray, noise_rad: float, gnorm: np.ndarray, local: np.ndarray,
                 reliable: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """(1-σ height per pixel, the factor (>= 1) by which the heights' own spread widened it, the pixels whose
    heights set that factor) of a pair whose flow noise across the epipolar lines is ``noise_rad`` (normalised
    units), with the range gain ``gain`` (range_gain), the parallax gradient norm ``gnorm`` and the heights above
    the local ground ``local``, of which ``reliable`` ones count.

    The across-epipolar spread misses errors along the epipolar lines (perspective change between the pair, DIS's
    smoothing): the measured heights' own robust spread, in units of that σ, corrects it (obstacles are a minority
    of the pixels; they can only inflate it, the safe direction).
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma0 = gain * noise_rad / gnorm
        z = np.abs(local) / sigma0
    usable = reliable & np.isfinite(z)
    widened = 1.0
    if int(usable.sum()) >= 100:
        scale = 1.4826 * float(np.median(z[usable]))
        if scale > 1.0:
            sigma0, widened = sigma0 * scale, scale
    return sigma0, widened, usable


def row_nanmedian(a: np.ndarray) -> np.ndarray:
    """``np.nanmedian(a, axis=1)`` of a small 2-D array, bit for bit (NaN for an all-NaN row, no warning).

    numpy takes a masked-array path for small inputs (~0.2 ms for 16×20, once per motion update); a sort
    and the two middle elements are ~15 µs. The mean of the two middles is (lo + hi) / 2, as numpy's.
    """
    s = np.sort(a, axis=1)                                    # NaN sorts last
    n = np.count_nonzero(~np.isnan(a), axis=1)
    lo = np.take_along_axis(s, np.maximum((n - 1) // 2, 0)[:, None], axis=1)[:, 0]
    hi = np.take_along_axis(s, np.minimum(n // 2, a.shape[1] - 1)[:, None], axis=1)[:, 0]
    out: np.ndarray = np.where(n > 0, (lo + hi) / 2, np.nan)
    return out


def _design(dn: np.ndarray, de: np.ndarray) -> np.ndarray:
    return np.stack([np.ones_like(dn), dn, de, dn * dn, dn * de, de * de], axis=-1)


def fit_ground(ned: np.ndarray, hgt: np.ndarray, sigma: np.ndarray, use: np.ndarray, here: np.ndarray,
                max_points: int = 3000, start_m: Optional[float] = None) -> np.ndarray:
    """Robust quadratic surface through the ground's heights (coefficients in 100 m units).

    Starts from the 10th percentile (obstacles sit above the ground; some ground shows between them), or
    from ``start_m`` when the surface's level is known (a roof the plane sweep found: the street beyond its
    edge must not become its ground), and trims to shrinking windows that reach less far up than down, so
    obstacles do not lift the surface.
    """
    coef = np.zeros(6)
    idx = np.flatnonzero(use.reshape(-1))
    if idx.size < 30:
        return coef
    if idx.size > max_points:
        idx = idx[:: idx.size // max_points + 1]
    h = hgt.reshape(-1)[idx]
    dn = (ned[0].reshape(-1)[idx] - here[0]) / 100.0
    de = (ned[1].reshape(-1)[idx] - here[1]) / 100.0
    a = _design(dn, de)
    coef[0] = float(np.percentile(h, 10)) if start_m is None else start_m
    for window in (3.0, 1.5, 0.6):
        res = h - a @ coef
        # Asymmetric: what stands out above the surface is left out sooner than what lies below it, so a
        # field packed with cars of one height does not become a raised "ground" at their roofs.
        inl = (res >= -window) & (res <= 0.3 * window)
        if inl.sum() < 30:
            break
        sol, *_ = np.linalg.lstsq(a[inl], h[inl], rcond=None)
        coef = sol
    return coef


def ground_surface(coef: np.ndarray, ned: np.ndarray, here: np.ndarray) -> np.ndarray:
    dn = (ned[0] - here[0]) / 100.0
    de = (ned[1] - here[1]) / 100.0
    out: np.ndarray = coef[0] + coef[1] * dn + coef[2] * de + coef[3] * dn * dn + coef[4] * dn * de \
        + coef[5] * de * de
    return out


def column_seen(pose: CameraPose, k_cv: np.ndarray, origin_uv: tuple[int, int], xc: np.ndarray, ned: np.ndarray,
                measured: np.ndarray, column_m: float, samples: int = 4, beyond_m: float = 1.0) -> np.ndarray:
    """Per window pixel: was the air above its ground point seen empty, up to ``column_m``?

    An oblique camera sees ground under an overhang (a tree crown, eaves) that a vertical descent would hit.
    The rays between a pixel and the image of the point ``column_m`` above its ground point pass over that
    point; where they end beyond it (``beyond_m``, or half as far beyond as the plane predicts when that is
    less: on a wall or a car behind the point, or on the ground), the air they crossed above it was empty.
    A pixel is not seen when its column leaves the window, or when one of ``samples`` rays on it was measured
    ending short (at something above the point: the side or underside of a crown); unmeasured pixels on the
    column are no evidence either way. ``xc``: normalised coordinates (2×H×W); ``ned``: the pixels' NED
    points at their measured heights (3×H×W); ``measured``: H×W; ``origin_uv``: the window's corner (column,
    row) in the frame. Pure numpy.
    """
    h, w = measured.shape
    c, r = pose.position_ned_m, pose.r_nc
    # Flat 3×N arrays and 3×3 matrix products: cheaper than einsums over H×W.
    dirs = r[:, :2] @ np.stack([xc[0].reshape(-1), xc[1].reshape(-1)]) + r[:, 2:3]
    ned_f, meas = ned.reshape(3, -1), measured.reshape(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        plane_m = np.where(dirs[2] > 0, pose.agl_m * np.hypot(dirs[0], dirs[1]) / dirs[2], np.nan)
        range_m = np.where(meas, np.hypot(ned_f[0] - c[0], ned_f[1] - c[1]), np.nan)
        top = r.T @ (ned_f - (c + np.array([0.0, 0.0, column_m]))[:, None])
        u_top = k_cv[0, 0] * top[0] / top[2] + k_cv[0, 2] - origin_uv[0]
        v_top = k_cv[1, 1] * top[1] / top[2] + k_cv[1, 2] - origin_uv[1]
    xx = np.tile(np.arange(w, dtype=np.float64), h)
    yy = np.repeat(np.arange(h, dtype=np.float64), w)
    seen = meas & (top[2] > 0) & np.isfinite(u_top) & np.isfinite(v_top)
    # A pixel's verdict depends only on its own column, and ``seen`` only ever turns False: the steps towards
    # the column's top can be fixed once, and the lookups done on the flat arrays.
    du, dv = np.where(seen, u_top - xx, 0.0), np.where(seen, v_top - yy, 0.0)
    for s in np.linspace(1.0 / samples, 1.0, samples):
        uq = np.rint(xx + s * du)
        vq = np.rint(yy + s * dv)
        inside = (uq >= 0) & (uq < w) & (vq >= 0) & (vq < h)
        flat = (np.clip(vq, 0, h - 1) * w + np.clip(uq, 0, w - 1)).astype(np.intp)
        with np.errstate(invalid="ignore"):
            short = range_m[flat] - range_m < np.minimum(0.5 * (plane_m[flat] - plane_m), beyond_m)
        seen &= inside & ~(meas[flat] & short)
    out: np.ndarray = seen.reshape(h, w)
    return out


def thin_factor(footprint_m: np.ndarray, thin_m: float) -> Optional[np.ndarray]:
    """How many times its detectable height an obstacle ``thin_m`` wide must stand to read as high, per pixel:
    the flow's patch footprint on the ground over that width, at least 1 (None: ``thin_m`` 0, not assumed)."""
    if thin_m <= 0:
        return None
    with np.errstate(invalid="ignore"):
        return np.maximum(footprint_m / thin_m, 1.0).astype(np.float32)
