"""Pure-numpy surface geometry: normals from depth and the HVO labels of ARCHITECTURE.md §4.

HVO from normals (the paper's §4.1 recipe): θ = angle between the surface normal and world up;
horizontal if θ <= horizontal_max, vertical if θ >= vertical_min, other in between; invalid -> 255.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from edge_landing.runtime.core.camera import Intrinsics
from edge_landing.runtime.core.labels import HVO_IGNORE

HORIZONTAL, VERTICAL, OTHER = 0, 1, 2


@dataclass(frozen=True)
class HvoThresholds:
    """Angles between the surface normal and world up, in radians (scene.json stores degrees)."""

    horizontal_max_rad: float = math.radians(10.0)
    vertical_min_rad: float = math.radians(80.0)

    def to_json(self) -> dict[str, float]:
        return {"horizontal_max_deg": math.degrees(self.horizontal_max_rad),
                "vertical_min_deg": math.degrees(self.vertical_min_rad)}

    @staticmethod
    def from_json(d: Mapping[str, Any]) -> HvoThresholds:
        return HvoThresholds(math.radians(float(d.get("horizontal_max_deg", 10.0))),
                             math.radians(float(d.get("vertical_min_deg", 80.0))))


def normals_from_points(points: np.ndarray) -> np.ndarray:
    """Unit normals H×W×3 from an organised point cloud H×W×3 (central differences, facing the camera).

    Pixels whose neighbours are invalid, and the one-pixel border, get NaN.
    """
    p = points.astype(np.float32, copy=False)
    du = np.full_like(p, np.nan)
    dv = np.full_like(p, np.nan)
    du[:, 1:-1] = p[:, 2:] - p[:, :-2]
    dv[1:-1, :] = p[2:, :] - p[:-2, :]
    n: np.ndarray = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / norm
    # Orient towards the camera: the normal must point against the viewing ray.
    flip = np.sum(n * p, axis=-1) > 0
    n[flip] *= -1.0
    return n


def normals_from_depth(depth_m: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """Camera-frame unit normals H×W×3 from planar z-depth (NaN where undefined)."""
    return normals_from_points(intrinsics.backproject(depth_m))


def slope_from_normals(normals: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Angle (radians) between each normal and the ``up`` vector given in the same frame (NaN stays NaN)."""
    cos = np.clip(normals @ np.asarray(up, dtype=np.float32), -1.0, 1.0)
    angle_rad: np.ndarray = np.arccos(cos)
    return angle_rad


def hvo_from_normals(normals: np.ndarray, up: np.ndarray, thresholds: HvoThresholds = HvoThresholds()) -> np.ndarray:
    """uint8 H×W labels 0/1/2, 255 where the normal is not finite."""
    theta = slope_from_normals(normals, up)
    labels = np.full(theta.shape, HVO_IGNORE, dtype=np.uint8)
    ok = np.isfinite(theta)
    labels[ok & (theta <= thresholds.horizontal_max_rad)] = HORIZONTAL
    labels[ok & (theta >= thresholds.vertical_min_rad)] = VERTICAL
    labels[ok & (theta > thresholds.horizontal_max_rad) & (theta < thresholds.vertical_min_rad)] = OTHER
    return labels
