"""Still water as a camera sees it: the floor through the surface, and the sky mirrored by Fresnel's law.

Still water has no texture of its own. What a camera sees on it either lies below the surface (the floor, seen
along the refracted ray, about three quarters of its depth down) or moves with the camera (the sky's mirror
image). Neither moves between two views like a point on the surface, so motion geometry reads water as
something below the ground plane or as noise, as it would over a real pool or pond; a texture painted on the
surface itself would read as level ground. Murky water shows no floor: only the sky and its own colour, a smooth
patch. Floating weed or scum, which would move with the surface, is not modelled.

World frame NED, metres. Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .world import Style

WATER_INDEX = 1.333
NORMAL_REFLECTANCE = 0.02            # water at normal incidence ((n - 1) / (n + 1))²


@dataclass(frozen=True)
class Water:
    """How deep and how clear. ``absorption_per_m``: per metre of path, red first; ``body_rgb``: the colour the
    water itself scatters back where the floor's light does not come through (silt, algae)."""

    floor_depth_m: float
    absorption_per_m: tuple[float, float, float]
    body_rgb: tuple[float, float, float]


CLEAR_POOL = Water(1.5, (0.45, 0.09, 0.06), (0.02, 0.10, 0.14))     # a garden pool: its floor shows
MURKY_POND = Water(1.5, (3.0, 2.2, 2.6), (0.16, 0.20, 0.13))        # a farm pond or canal: nothing below 0.3 m


def water_of(style: Style) -> Water:
    """Towns have garden pools; the countryside has ponds and canals."""
    return MURKY_POND if style is Style.RURAL else CLEAR_POOL


def _unit(v: np.ndarray) -> np.ndarray:
    return np.asarray(v / np.linalg.norm(v, axis=1, keepdims=True), np.float64)


def floor_points(points_ned: np.ndarray, dirs_ned: np.ndarray, normals_ned: np.ndarray,
                 depth_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(K×3 floor points, K path lengths in water) for K surface hits: each view ray refracted at the surface
    (Snell) and followed ``depth_m`` down to a level floor. ``normals_ned`` face the camera."""
    d, n = _unit(dirs_ned), _unit(normals_ned.astype(np.float64))
    cos_i = -np.sum(d * n, axis=1, keepdims=True)
    eta = 1.0 / WATER_INDEX
    cos_t = np.sqrt(np.clip(1.0 - eta ** 2 * (1.0 - cos_i ** 2), 0.0, 1.0))
    t = eta * d + (eta * cos_i - cos_t) * n                 # refracted direction, unit, into the water
    down = np.maximum(t[:, 2:3], 1e-3)                      # NED: +z is down
    path = depth_m / down
    return points_ned + t * path, path[:, 0]


def fresnel(dirs_ned: np.ndarray, normals_ned: np.ndarray) -> np.ndarray:
    """K reflectances (Schlick's approximation) for view rays hitting water with camera-facing normals."""
    cos_i = np.clip(-np.sum(_unit(dirs_ned) * _unit(normals_ned.astype(np.float64)), axis=1), 0.0, 1.0)
    return (NORMAL_REFLECTANCE + (1.0 - NORMAL_REFLECTANCE) * (1.0 - cos_i) ** 5).astype(np.float32)


def below_surface(water: Water, floor_light: np.ndarray, light: np.ndarray, path_m: np.ndarray) -> np.ndarray:
    """K×3 light from below the surface: the floor's (``floor_light``: its albedo under the light), dimmed on its
    way down (sunlight, about vertical) and back along the view ray, plus what the water scatters itself."""
    k = np.asarray(water.absorption_per_m, np.float32)[None, :]
    trans = np.exp(-k * (path_m[:, None] + water.floor_depth_m)).astype(np.float32)
    return floor_light * trans + np.asarray(water.body_rgb, np.float32)[None, :] * light * (1.0 - trans)
