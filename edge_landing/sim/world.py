"""Procedural worlds: triangle meshes with per-triangle materials, a terrain heightfield and a ground map.

World frame = local NED (x north, y east, z down, metres); the ground is near z = 0, so heights above the
ground are negative z. Terrain triangles carry ``Material.TERRAIN``; what the ground looks like there
(grass, asphalt, markings, pavement…) comes from a 0.25 m ground map looked up at the hit point, so roads and
lawns cost no triangles. Ray casting uses Embree (embreex) directly: one ``EmbreeScene`` per world.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum
from functools import lru_cache

import numpy as np
import numpy.typing as npt

from edge_landing.runtime.core.choices import ChoiceEnum
from edge_landing.runtime.core.errors import require_extra

from .meshes import Part

WORLD_HALF_SIZE_M = 600.0           # 1.2 km square: a 45° view from 90 m still hits ground ~600 m out
GROUND_MAP_RES_M = 0.25
TERRAIN_STEP_M = 10.0
MISS = -1


class Material(IntEnum):
    TERRAIN = 0        # resolved through the ground map
    GRASS = 1
    ASPHALT = 2
    MARKING = 3
    CONCRETE = 4       # sidewalks, driveways
    PAVING = 5         # plazas
    SOIL = 6
    ROOF_TILE = 7
    ROOF_FLAT = 8
    WALL = 9           # house walls (plaster, brick)
    FACADE = 10        # urban facades with windows
    FOLIAGE = 11
    TRUNK = 12
    CAR_PAINT = 13
    GLASS = 14
    CLUTTER = 15       # roof units, kiosks
    CURTAIN_WALL = 16  # glass office facades
    WATER = 17         # garden pools


# What a drone must not land on whatever its surface's slope: a tree crown's or a car roof's top faces up, a
# pond is level, a person's shoulders too. The "landing" label rule (LabelRule) calls them OTHER.
NOT_GROUND = (Material.FOLIAGE, Material.TRUNK, Material.CAR_PAINT, Material.GLASS, Material.CLUTTER,
              Material.WATER)


class LabelRule(ChoiceEnum):
    """How HVO labels are made. GEOMETRY: from the surface normal alone (the paper's AirSimNC and SafeUAV
    definition). LANDING (default): the same, but vegetation, vehicles, clutter, people and water are OTHER
    whatever their slope, so that "horizontal" means level ground or built surface a drone may land on."""

    LANDING = "landing"
    GEOMETRY = "geometry"

    @classmethod
    def _label(cls) -> str:
        return "label rule"


class Style(ChoiceEnum):
    SUBURBAN = "suburban"
    URBAN = "urban"
    RURAL = "rural"     # held out of training: the zero-shot test style (sim/rural.py)

    @classmethod
    def _label(cls) -> str:
        return "world style"


@dataclass(frozen=True)
class Terrain:
    """A gentle heightfield on a regular grid; ``z`` holds NED down values (metres) at the grid nodes."""

    z: np.ndarray              # (n_rows, n_cols), row = north index, col = east index
    origin_m: float            # north/east of node (0, 0)
    step_m: float

    def z_at(self, north: np.ndarray, east: np.ndarray) -> np.ndarray:
        """Exact z of the terrain mesh (same triangle split as :meth:`triangles`)."""
        fi = np.clip((np.asarray(north, np.float64) - self.origin_m) / self.step_m, 0, self.z.shape[0] - 1.000001)
        fj = np.clip((np.asarray(east, np.float64) - self.origin_m) / self.step_m, 0, self.z.shape[1] - 1.000001)
        i, j = np.floor(fi).astype(int), np.floor(fj).astype(int)
        a, b = fi - i, fj - j
        z00, z10, z01, z11 = self.z[i, j], self.z[i + 1, j], self.z[i, j + 1], self.z[i + 1, j + 1]
        lower = a >= b            # triangle (00, 10, 11) else (00, 11, 01)
        return np.where(lower, z00 + a * (z10 - z00) + b * (z11 - z10), z00 + b * (z01 - z00) + a * (z11 - z01))

    def z_at_point(self, north: float, east: float) -> float:
        """Scalar :meth:`z_at` without numpy overhead (layouts call it thousands of times)."""
        rows, cols = self.z.shape
        fi = min(max((north - self.origin_m) / self.step_m, 0.0), rows - 1.000001)
        fj = min(max((east - self.origin_m) / self.step_m, 0.0), cols - 1.000001)
        i, j = int(fi), int(fj)
        a, b = fi - i, fj - j
        z = self.z
        if a >= b:
            return float(z[i, j] + a * (z[i + 1, j] - z[i, j]) + b * (z[i + 1, j + 1] - z[i + 1, j]))
        return float(z[i, j] + b * (z[i, j + 1] - z[i, j]) + a * (z[i + 1, j + 1] - z[i, j + 1]))

    def triangles(self) -> np.ndarray:
        n = self.origin_m + self.step_m * np.arange(self.z.shape[0])
        e = self.origin_m + self.step_m * np.arange(self.z.shape[1])
        nn, ee = np.meshgrid(n, e, indexing="ij")
        p = np.stack([nn, ee, self.z], axis=-1)
        p00, p10, p01, p11 = p[:-1, :-1], p[1:, :-1], p[:-1, 1:], p[1:, 1:]
        t1 = np.stack([p00, p10, p11], axis=-2).reshape(-1, 3, 3)
        t2 = np.stack([p00, p11, p01], axis=-2).reshape(-1, 3, 3)
        return np.concatenate([t1, t2])


def make_terrain(rng: np.random.Generator, amplitude_m: float) -> Terrain:
    """Sum of a few long plane waves: slopes stay a few degrees, so open ground is 'horizontal'."""
    n_nodes = int(round(2 * WORLD_HALF_SIZE_M / TERRAIN_STEP_M)) + 1
    coords = -WORLD_HALF_SIZE_M + TERRAIN_STEP_M * np.arange(n_nodes)
    nn, ee = np.meshgrid(coords, coords, indexing="ij")
    h = np.zeros_like(nn)
    for _ in range(5):
        wavelength = rng.uniform(250.0, 700.0)
        ang, phase = rng.uniform(0, 2 * math.pi), rng.uniform(0, 2 * math.pi)
        k = 2 * math.pi / wavelength
        h += rng.uniform(0.3, 1.0) * np.sin(k * (nn * math.cos(ang) + ee * math.sin(ang)) + phase)
    h *= amplitude_m / max(np.abs(h).max(), 1e-6)
    return Terrain(z=-h, origin_m=-WORLD_HALF_SIZE_M, step_m=TERRAIN_STEP_M)


class GroundMap:
    """A north/east raster of ground materials painted with OpenCV polygons (cell = GROUND_MAP_RES_M)."""

    def __init__(self, base: Material):
        self.size = int(round(2 * WORLD_HALF_SIZE_M / GROUND_MAP_RES_M))
        self.cells = np.full((self.size, self.size), int(base), np.uint8)    # row = north, col = east

    def _px(self, north, east) -> np.ndarray:
        # cv2 points are (x=col=east, y=row=north), fixed point with 4 fractional bits.
        col = (np.asarray(east, np.float64) + WORLD_HALF_SIZE_M) / GROUND_MAP_RES_M - 0.5
        row = (np.asarray(north, np.float64) + WORLD_HALF_SIZE_M) / GROUND_MAP_RES_M - 0.5
        return np.round(np.stack([col, row], axis=-1) * 16).astype(np.int32)

    def rects(self, n0: npt.ArrayLike, e0: npt.ArrayLike, n1: npt.ArrayLike, e1: npt.ArrayLike,
              material: Material) -> None:
        """Axis-aligned rectangles (arrays of corners, metres)."""
        import cv2

        n0, e0, n1, e1 = (np.atleast_1d(np.asarray(a, np.float64)) for a in (n0, e0, n1, e1))
        if n0.size == 0:
            return
        corners = np.stack([np.stack([n0, e0], -1), np.stack([n0, e1], -1), np.stack([n1, e1], -1),
                            np.stack([n1, e0], -1)], axis=1)
        polys = self._px(corners[..., 0], corners[..., 1])
        cv2.fillPoly(self.cells, list(polys), int(material), lineType=cv2.LINE_8, shift=4)

    def lookup(self, north: np.ndarray, east: np.ndarray) -> np.ndarray:
        row = np.clip(((north + WORLD_HALF_SIZE_M) / GROUND_MAP_RES_M).astype(np.int64), 0, self.size - 1)
        col = np.clip(((east + WORLD_HALF_SIZE_M) / GROUND_MAP_RES_M).astype(np.int64), 0, self.size - 1)
        return self.cells[row, col]


@dataclass
class World:
    """A built world. ``tris`` float32 M×3×3, ``normals`` float32 M×3 (unit, arbitrary side)."""

    style: Style
    seed: int
    tris: np.ndarray
    material: np.ndarray
    tint: np.ndarray
    normals: np.ndarray
    terrain: Terrain
    ground: GroundMap
    landing_spots: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))   # open flat ground (n, e)
    _scene: object = None

    @property
    def scene(self):
        if self._scene is None:
            rtcs = require_extra("embreex.rtcore_scene", "sim")
            mesh_construction = require_extra("embreex.mesh_construction", "sim")
            self._scene = rtcs.EmbreeScene()
            mesh_construction.TriangleMesh(self._scene, self.tris)
        return self._scene

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hits along rays: (t, triangle index); t is in units of ``dirs``' length, MISS index = -1.

        Passing camera rays K⁻¹[u, v, 1] rotated to the world makes t the planar z-depth directly.
        """
        res = self.scene.run(np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(dirs, np.float32),
                             output=1)
        prim = res["primID"].astype(np.int64)
        t = res["tfar"].astype(np.float64)
        t[prim == MISS] = np.nan
        return t, prim

    def occluded(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """True where anything lies along the ray (shadow rays)."""
        res = self.scene.run(np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(dirs, np.float32),
                             query="OCCLUDED")
        return res != MISS

    def surface_z(self, north: np.ndarray, east: np.ndarray) -> np.ndarray:
        """z of the first surface straight below a point high above (what a down rangefinder sees)."""
        north, east = np.atleast_1d(north), np.atleast_1d(east)
        o = np.stack([north, east, np.full(north.shape, -1000.0)], axis=-1)
        d = np.broadcast_to(np.array([0.0, 0.0, 1.0]), o.shape)
        t, prim = self.intersect(o, d)
        return np.where(prim == MISS, self.terrain.z_at(north, east), -1000.0 + t)

    def materials_at(self, prim: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Material per hit (uint8), terrain resolved through the ground map; MISS -> 255."""
        out = np.full(prim.shape, 255, np.uint8)
        hit = prim != MISS
        out[hit] = self.material[prim[hit]]
        terr = hit & (out == Material.TERRAIN)
        out[terr] = self.ground.lookup(points[terr, 0], points[terr, 1])
        return out


def _finish(style: Style, seed: int, part: Part, terrain: Terrain, ground: GroundMap, spots: np.ndarray) -> World:
    terrain_tris = terrain.triangles()
    tris = np.concatenate([terrain_tris, part.tris]).astype(np.float32)
    material = np.concatenate([np.full(len(terrain_tris), Material.TERRAIN, np.uint8), part.material])
    tint = np.concatenate([np.ones((len(terrain_tris), 3), np.float32), part.tint])
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]).astype(np.float64)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    keep = norm[:, 0] > 1e-9                               # drop degenerate triangles
    normals = (n[keep] / norm[keep]).astype(np.float32)
    return World(style, seed, np.ascontiguousarray(tris[keep]), material[keep], tint[keep], normals, terrain,
                 ground, spots)


@lru_cache(maxsize=4)
def build_world(style: Style | str, seed: int, hazards: bool = False, people: bool = False) -> World:
    """The world for (style, seed): deterministic, cached per process (a second call is free).

    ``hazards``: cars, bushes, trees, low walls, poles and clutter around the landing spots (sim.hazards),
    from their own Generator, so the town's layout does not depend on it. Off by default: the existing
    seeds' tests judge the network alone, which these hazards defeat (edge-sim --hazards, lying_model).
    ``people``: people standing around the landing spots (sim.hazards.people_part), from a Generator of their
    own, so a world with people is the same world otherwise (lying_model --people).
    """
    from .towns import suburban_layout, urban_layout

    style = style if isinstance(style, Style) else Style.from_string(style)
    style_key = {Style.SUBURBAN: 0, Style.URBAN: 1}.get(style, 2)
    rng = np.random.default_rng([int(seed), 0x5EED, style_key])
    if style is Style.RURAL:
        from .rural import rural_layout

        terrain = make_terrain(rng, amplitude_m=4.0)
        ground = GroundMap(Material.GRASS)
        part, spots = rural_layout(rng, terrain, ground)
    elif style is Style.SUBURBAN:
        terrain = make_terrain(rng, amplitude_m=3.0)
        ground = GroundMap(Material.GRASS)
        part, spots = suburban_layout(rng, terrain, ground)
    else:
        terrain = make_terrain(rng, amplitude_m=1.0)
        ground = GroundMap(Material.CONCRETE)
        part, spots = urban_layout(rng, terrain, ground)
    if hazards:
        from .hazards import hazard_part

        hazard_rng = np.random.default_rng([int(seed), 0x4A2A, 1 if style is Style.URBAN else 0])
        part = Part.concat([part, hazard_part(hazard_rng, terrain, spots)])
    if people:
        from .hazards import people_part

        people_rng = np.random.default_rng([int(seed), 0x9E0, style_key])
        part = Part.concat([part, people_part(people_rng, terrain, spots)])
    return _finish(style, int(seed), part, terrain, ground, spots)
