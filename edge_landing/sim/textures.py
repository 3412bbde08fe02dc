"""Procedural textures: per-material albedo at world points, from tileable noise and simple patterns.

Textures are looked up in world coordinates (metres), so a surface looks the same from every pose and at
every image size. Horizontal-ish surfaces use (north, east); walls use (distance along the wall, height).
Colours are display-referred RGB in [0, 1]; the per-triangle tint multiplies the patterned base colour.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from .world import Material, World

TILE = 256
_BASE = {
    Material.GRASS: (0.30, 0.44, 0.17), Material.ASPHALT: (0.27, 0.27, 0.28), Material.MARKING: (0.88, 0.88, 0.84),
    Material.CONCRETE: (0.63, 0.62, 0.59), Material.PAVING: (0.66, 0.58, 0.50), Material.SOIL: (0.46, 0.37, 0.26),
    Material.ROOF_TILE: (1.0, 1.0, 1.0), Material.ROOF_FLAT: (1.0, 1.0, 1.0), Material.WALL: (1.0, 1.0, 1.0),
    Material.FACADE: (1.0, 1.0, 1.0), Material.FOLIAGE: (0.20, 0.33, 0.12), Material.TRUNK: (0.30, 0.22, 0.15),
    Material.CAR_PAINT: (1.0, 1.0, 1.0), Material.GLASS: (0.10, 0.12, 0.15), Material.CLUTTER: (0.85, 0.85, 0.85),
    Material.TERRAIN: (0.30, 0.44, 0.17), Material.CURTAIN_WALL: (0.30, 0.36, 0.42), Material.WATER: (0.62, 0.76, 0.78),
}


@lru_cache(maxsize=1)
def noise_tiles() -> np.ndarray:
    """Four tileable noise tiles (fine to coarse), zero mean, unit-ish spread: shape 4×TILE×TILE float32.

    Built from white noise filtered in the Fourier domain, so they wrap seamlessly. Fixed seed: textures are
    part of the renderer, not of the world's randomness.
    """
    rng = np.random.default_rng(1234)
    f = np.fft.fftfreq(TILE)
    r = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    tiles = []
    for cutoff in (0.35, 0.12, 0.05, 0.02):
        spec = np.fft.fft2(rng.standard_normal((TILE, TILE))) * np.exp(-(r / cutoff) ** 2)
        t = np.real(np.fft.ifft2(spec))
        tiles.append((t - t.mean()) / (t.std() + 1e-9))
    return np.stack(tiles).astype(np.float32)


def _sample(octave: int, u: np.ndarray, v: np.ndarray, cells_per_m: float) -> np.ndarray:
    tile = noise_tiles()[octave]
    return tile[(u * cells_per_m).astype(np.int64) & (TILE - 1), (v * cells_per_m).astype(np.int64) & (TILE - 1)]


def _frac(x: np.ndarray) -> np.ndarray:
    return x - np.floor(x)


def _hash(i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """A cheap deterministic per-cell value in [0, 1)."""
    h = (i.astype(np.int64) * 73856093) ^ (j.astype(np.int64) * 19349663)
    return ((h & 0xFFFF) / 65536.0).astype(np.float32)


def albedo(world: World, material: np.ndarray, tri: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """K×3 float32 albedo for K hits: material ids, triangle ids, world points and unit world normals."""
    k = material.shape[0]
    out = np.empty((k, 3), np.float32)
    base = np.array([_BASE.get(Material(m), (1.0, 1.0, 1.0)) for m in range(max(Material) + 1)], np.float32)
    out[:] = base[material] * world.tint[tri]
    n, e, z = points[:, 0], points[:, 1], points[:, 2]
    flat = np.abs(normals[:, 2]) > 0.5
    # Along-wall coordinate: horizontal tangent (-n_e, n_n) to the wall's normal.
    s = np.where(flat, n, -n * normals[:, 1] + e * normals[:, 0])
    t = np.where(flat, e, z)
    shade = np.ones(k, np.float32)

    def sel(mat):
        return np.nonzero(material == mat)[0]

    idx = sel(Material.GRASS)
    if idx.size:
        patch = _sample(3, s[idx], t[idx], 4.0)
        shade[idx] = 1 + 0.18 * patch + 0.12 * _sample(0, s[idx], t[idx], 8.0)
        out[idx, 0] *= 1 + 0.12 * np.clip(patch, 0, None)          # dry, yellower patches
    for mat, amp, cells in ((Material.ASPHALT, 0.10, 6.0), (Material.SOIL, 0.15, 4.0), (Material.TRUNK, 0.2, 8.0)):
        idx = sel(mat)
        if idx.size:
            shade[idx] = 1 + amp * _sample(0, s[idx], t[idx], cells) + 0.6 * amp * _sample(2, s[idx], t[idx], 1.0)
    idx = sel(Material.MARKING)
    if idx.size:
        shade[idx] = 1 - 0.15 * np.clip(_sample(1, s[idx], t[idx], 6.0), 0, None)
    idx = sel(Material.CONCRETE)
    if idx.size:
        joints = (_frac(s[idx] / 1.5) < 0.05) | (_frac(t[idx] / 1.5) < 0.05)
        shade[idx] = (1 + 0.06 * _sample(0, s[idx], t[idx], 6.0) + 0.05 * _sample(2, s[idx], t[idx], 1.0)) * \
            np.where(joints, 0.82, 1.0)
    idx = sel(Material.PAVING)
    if idx.size:
        i, j = np.floor(s[idx] / 0.6), np.floor(t[idx] / 0.6)
        gap = (_frac(s[idx] / 0.6) < 0.08) | (_frac(t[idx] / 0.6) < 0.08)
        shade[idx] = (0.88 + 0.22 * _hash(i, j)) * np.where(gap, 0.75, 1.0)
    idx = sel(Material.ROOF_TILE)
    if idx.size:
        # Rows of tiles run across the slope: coordinate along the downslope direction.
        hn = normals[idx, :2] / (np.linalg.norm(normals[idx, :2], axis=1, keepdims=True) + 1e-6)
        d = n[idx] * hn[:, 0] + e[idx] * hn[:, 1]
        across = -n[idx] * hn[:, 1] + e[idx] * hn[:, 0]
        row = np.floor(d / 0.33)
        seam = (_frac(d / 0.33) < 0.18) | (_frac(across / 0.3 + 0.5 * row) < 0.08)
        shade[idx] = (0.92 + 0.1 * _hash(row, np.floor(across / 0.3)) + 0.06 * _sample(2, n[idx], e[idx], 1.0)) * \
            np.where(seam, 0.72, 1.0)
    for mat in (Material.ROOF_FLAT, Material.CLUTTER):
        idx = sel(mat)
        if idx.size:
            shade[idx] = 1 + 0.08 * _sample(0, s[idx], t[idx], 10.0) + 0.1 * _sample(2, s[idx], t[idx], 0.7)
    idx = sel(Material.FOLIAGE)
    if idx.size:
        # Leaf clumps: per-facet brightness (low-poly crowns read as foliage) times fine noise.
        facet = _hash(tri[idx], tri[idx] // 7)
        shade[idx] = (0.8 + 0.4 * facet) * (1 + 0.25 * _sample(0, n[idx] + 0.3 * z[idx], e[idx] - 0.3 * z[idx], 9.0))
    idx = sel(Material.CURTAIN_WALL)
    if idx.size:
        # Glass panels reflecting the sky unevenly, framed by mullions every 1.5 m and each floor.
        panel = _hash(np.floor(s[idx] / 1.5), np.floor(z[idx] / 3.4))
        mullion = (_frac(s[idx] / 1.5) < 0.06) | (_frac(z[idx] / 3.4) < 0.08)
        shade[idx] = np.where(mullion, 0.55, 0.8 + 0.5 * panel)
    idx = sel(Material.WATER)
    if idx.size:
        # The floor under the water (render.py looks it up where the refracted ray meets it; sim.water).
        shade[idx] = 1 + 0.15 * _sample(1, s[idx], t[idx], 5.0) + 0.08 * _sample(0, s[idx], t[idx], 10.0)
    idx = sel(Material.CAR_PAINT)
    if idx.size:
        shade[idx] = 1 + 0.03 * _sample(1, s[idx], t[idx], 4.0)
    _windows(world, material, s, z, n, e, out, shade)
    out *= np.clip(shade, 0.3, 1.8)[:, None]
    return np.clip(out, 0.0, 1.0)


def _windows(world: World, material, s, z, n, e, out, shade) -> None:
    """Windows on walls (houses: sparse, facades: a regular grid of glass per floor)."""
    for mat, pitch_m, floor_m, width_frac, sill_m, top_m in ((Material.WALL, 4.0, 2.9, 0.3, 1.0, 2.1),
                                                          (Material.FACADE, 3.0, 3.4, 0.62, 0.9, 2.8)):
        idx = np.nonzero(material == mat)[0]
        if not idx.size:
            continue
        height = world.terrain.z_at(n[idx], e[idx]) - z[idx]
        in_floor = np.mod(height, floor_m)
        col = _frac(s[idx] / pitch_m)
        glass = (np.abs(col - 0.5) < width_frac / 2) & (in_floor > sill_m) & (in_floor < top_m) & (height > 0.5)
        if not glass.any():
            continue
        g = idx[glass]
        bright = 0.6 + 0.8 * _hash(np.floor(s[g] / pitch_m), np.floor(height[glass] / floor_m))
        out[g] = np.array([0.16, 0.19, 0.24], np.float32) * bright[:, None]
        shade[g] = 1.0
