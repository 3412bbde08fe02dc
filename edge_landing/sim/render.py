"""Ray-cast rendering of a world from a camera pose: ground truth (depth, normals, HVO, material) and RGB.

Rays are the runtime's own: ``Intrinsics.pixel_rays()`` (pixel centres, K⁻¹[u+0.5, v+0.5, 1]) rotated by
``ned_from_camera(mount, attitude)``. Because the camera rays have z = 1, the hit distance Embree reports is
the planar z-depth itself. Shading: sun (Lambert, cast shadows by shadow rays) + sky ambient, then
atmosphere and sensor effects (see :mod:`sim.effects`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

import numpy as np

from edge_landing.runtime.core.camera import (
    Attitude,
    Intrinsics,
    Mount,
    ned_from_camera,
    up_in_camera,
)
from edge_landing.runtime.core.geometry import OTHER, HvoThresholds, hvo_from_normals

from .effects import Effects, apply_atmosphere, apply_sensor, sky_colour, sun_colour
from .textures import albedo
from .water import below_surface, floor_points, fresnel, water_of
from .world import MISS, NOT_GROUND, LabelRule, Material, World

if TYPE_CHECKING:
    from .appearance import Palette

SKY_MATERIAL = 255
REFLECTANCE = np.zeros(256, np.float32)
REFLECTANCE[[Material.GLASS, Material.CURTAIN_WALL, Material.CAR_PAINT]] = (0.35, 0.3, 0.08)   # water: sim.water
_NOT_GROUND = np.zeros(256, bool)
_NOT_GROUND[list(NOT_GROUND)] = True


def _mirrored(dirs: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """K×3 unit directions of view rays ``dirs`` mirrored at surfaces with unit ``normals``."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    n = normals.astype(np.float64)
    out: np.ndarray = d - 2.0 * np.sum(d * n, axis=1, keepdims=True) * n
    return out


@dataclass(frozen=True)
class Geometry:
    """Per-pixel ray-cast truth. Arrays are H×W(×3); sky = NaN / 255 / -1."""

    depth_m: np.ndarray        # float32 planar z-depth
    normals: np.ndarray        # float32 unit normals in the camera frame, facing the camera
    hvo: np.ndarray            # uint8 0/1/2, 255 sky
    material: np.ndarray       # uint8 sim.world.Material, 255 sky
    triangle: np.ndarray       # int64 triangle index, -1 sky
    points_ned: np.ndarray     # float64 world points (NaN sky)
    normals_ned: np.ndarray    # float32 world normals facing the camera
    dirs_ned: np.ndarray       # float64 world ray directions (camera z = 1)


@dataclass(frozen=True)
class Rendering:
    rgb: np.ndarray            # uint8 H×W×3
    geometry: Geometry
    effects: Effects


class Renderer:
    """Renders one world through one camera model; reuse it for many poses."""

    def __init__(self, world: World, intrinsics: Intrinsics, mount: Mount = Mount(),
                 thresholds: HvoThresholds = HvoThresholds(), shadow_stride: int = 1,
                 labels: LabelRule = LabelRule.LANDING):
        self.world, self.intrinsics, self.mount, self.thresholds = world, intrinsics, mount, thresholds
        self.labels = LabelRule(labels)
        self.shadow_stride = max(1, int(shadow_stride))
        self.palette: Optional[Palette] = None     # edge-sim --randomise: the scene's material look
        rays = intrinsics.pixel_rays()
        self._rays_cam = rays.reshape(-1, 3).astype(np.float64)
        self._ray_length = np.linalg.norm(rays, axis=-1)           # range = z-depth × this

    def geometry(self, position_ned: np.ndarray, attitude: Attitude) -> Geometry:
        h, w = self.intrinsics.height, self.intrinsics.width
        rot = ned_from_camera(self.mount, attitude)                # v_ned = rot @ v_cam
        origin = np.asarray(position_ned, np.float64)
        dirs = self._rays_cam @ rot.T
        t, tri = self.world.intersect(np.broadcast_to(origin, dirs.shape), dirs)
        idx = np.flatnonzero(tri != MISS)
        n_hit = self.world.normals[tri[idx]]
        d_hit = dirs[idx]
        n_hit[np.einsum("ij,ij->i", n_hit, d_hit) > 0] *= -1.0     # face the camera
        points = np.full(dirs.shape, np.nan)
        points[idx] = origin + d_hit * t[idx, None]
        n_w = np.full(dirs.shape, np.nan, np.float32)
        n_w[idx] = n_hit
        n_cam = np.full(dirs.shape, np.nan, np.float32)
        n_cam[idx] = n_hit @ rot.astype(np.float32)                # rot.T @ n for each row
        normals = n_cam.reshape(h, w, 3)
        hvo = hvo_from_normals(normals, up_in_camera(self.mount, attitude), self.thresholds)
        material = self.world.materials_at(tri, points)
        if self.labels is LabelRule.LANDING:
            hvo[_NOT_GROUND[material].reshape(h, w)] = OTHER
        return Geometry(depth_m=t.reshape(h, w).astype(np.float32), normals=normals, hvo=hvo,
                        material=material.reshape(h, w), triangle=tri.reshape(h, w),
                        points_ned=points.reshape(h, w, 3), normals_ned=n_w.reshape(h, w, 3),
                        dirs_ned=dirs.reshape(h, w, 3))

    def _sunlit(self, g: Geometry, sun: np.ndarray, lambert: np.ndarray) -> np.ndarray:
        """H×W: 1 where the sun reaches the point (shadow rays cast at every ``shadow_stride``-th pixel)."""
        h, w = lambert.shape
        s = self.shadow_stride
        pts, nrm, lam = g.points_ned[::s, ::s], g.normals_ned[::s, ::s], lambert[::s, ::s]
        need = lam > 0
        lit: np.ndarray = np.zeros(lam.shape, np.float32)
        if need.any():
            # Push the origin off the surface; Embree's float32 error grows with the distance travelled.
            offset = 0.03 + 3e-4 * g.depth_m[::s, ::s][need][:, None].astype(np.float64)
            o = pts[need] + nrm[need] * offset
            lit[need] = ~self.world.occluded(o, np.broadcast_to(sun, o.shape))
        if s > 1:
            import cv2

            lit = cv2.resize(lit, (w, h), interpolation=cv2.INTER_LINEAR)
            lit[lambert <= 0] = 0.0
        return lit

    @staticmethod
    def _reflections(material: np.ndarray, dirs: np.ndarray, normals: np.ndarray, effects: Effects) -> np.ndarray:
        """Sky mirrored in glass, water and car paint (no inter-reflection: the sky only)."""
        out = np.zeros(dirs.shape, np.float32)
        k = REFLECTANCE[material]
        idx = np.flatnonzero(k > 0)
        if idx.size:
            out[idx] = k[idx, None] * sky_colour(_mirrored(dirs[idx], normals[idx]), effects)
        return out

    def _surfaces(self, mat: np.ndarray, tri: np.ndarray, points: np.ndarray, dirs: np.ndarray, normals: np.ndarray,
                  light: np.ndarray, effects: Effects) -> np.ndarray:
        """K×3 radiance of K hits: textured albedo under ``light`` plus the sky's reflection. Water's texture
        is its floor's, looked up where the refracted ray meets it (sim.water)."""
        water = np.flatnonzero(mat == Material.WATER)
        kind = water_of(self.world.style)
        tex_points, path_m = points, np.zeros(0)
        if water.size:
            tex_points = points.copy()
            tex_points[water], path_m = floor_points(points[water], dirs[water], normals[water], kind.floor_depth_m)
        alb = albedo(self.world, mat, tri, tex_points, normals)
        if self.palette is not None:
            alb = self.palette.apply(alb, mat, tri, tex_points)
        out = alb * light + self._reflections(mat, dirs, normals, effects)
        if water.size:
            r = fresnel(dirs[water], normals[water])
            out[water] = (1.0 - r)[:, None] * below_surface(kind, out[water], light[water], path_m) \
                + r[:, None] * sky_colour(_mirrored(dirs[water], normals[water]), effects)
        return np.asarray(out, np.float32)

    def render(self, position_ned: np.ndarray, attitude: Attitude, effects: Effects,
               rng: np.random.Generator) -> Rendering:
        g = self.geometry(position_ned, attitude)
        h, w = g.depth_m.shape
        sky = g.triangle == MISS
        hit = ~sky
        sun = effects.sun_direction_ned
        lambert = np.zeros((h, w), np.float32)
        n_hit = g.normals_ned[hit]
        lambert[hit] = np.clip(n_hit @ sun.astype(np.float32), 0.0, None)
        lit = self._sunlit(g, sun, lambert)
        rgb = np.empty((h, w, 3), np.float32)
        if hit.any():
            ambient = np.array([0.42, 0.47, 0.56], np.float32) * (0.55 - 0.45 * n_hit[:, 2:3])
            light = sun_colour(effects) * (lambert[hit] * lit[hit] * 0.95)[:, None] + ambient
            mat = g.material[hit]
            rgb[hit] = self._surfaces(mat, g.triangle[hit], g.points_ned[hit], g.dirs_ned[hit], n_hit, light, effects)
        dirs = g.dirs_ned[sky]
        rgb[sky] = sky_colour(dirs / np.linalg.norm(dirs, axis=1, keepdims=True), effects)
        rgb = apply_atmosphere(rgb, g.depth_m * self._ray_length, sky, effects)
        return Rendering(rgb=apply_sensor(rgb, effects, rng), geometry=g, effects=effects)
