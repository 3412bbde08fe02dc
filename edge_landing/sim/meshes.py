"""Vectorised builders for the low-poly primitives the worlds are made of.

Every builder takes arrays with one entry per instance and returns a ``Part``: triangles (M×3×3, local NED
metres: x north, y east, z down) with a per-triangle material id and RGB tint. Building thousands of
houses, trees and cars this way takes milliseconds instead of seconds (no per-object Python loop).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence

import numpy as np


@dataclass(frozen=True)
class Part:
    """A bag of triangles: ``tris`` float64 M×3×3, ``material`` uint8 M, ``tint`` float32 M×3."""

    tris: np.ndarray
    material: np.ndarray
    tint: np.ndarray

    @staticmethod
    def empty() -> Part:
        return Part(np.zeros((0, 3, 3)), np.zeros(0, np.uint8), np.zeros((0, 3), np.float32))

    @staticmethod
    def concat(parts: Sequence[Part]) -> Part:
        parts = [p for p in parts if len(p.tris)]
        if not parts:
            return Part.empty()
        return Part(np.concatenate([p.tris for p in parts]), np.concatenate([p.material for p in parts]),
                    np.concatenate([p.tint for p in parts]))


def _part(tris: np.ndarray, material, tint: np.ndarray, per_instance: int) -> Part:
    """Flatten instance-major triangles (K×T×3×3) and broadcast per-instance material / tint."""
    k = tris.shape[0]
    mat = np.broadcast_to(np.asarray(material, np.uint8).reshape(-1, 1) if np.ndim(material) else
                          np.full((k, 1), material, np.uint8), (k, per_instance))
    tint = np.broadcast_to(np.asarray(tint, np.float32).reshape(k, 1, 3), (k, per_instance, 3))
    return Part(tris.reshape(-1, 3, 3), mat.reshape(-1).copy(), tint.reshape(-1, 3).copy())


def _place(local: np.ndarray, cn: np.ndarray, ce: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Rotate instance-local points (K×...×3, x along the instance's length) by yaw and move them to (cn, ce)."""
    c, s = np.cos(yaw), np.sin(yaw)
    shape = (-1,) + (1,) * (local.ndim - 2)
    c, s, cn, ce = (np.asarray(a, np.float64).reshape(shape) for a in (c, s, cn, ce))
    out = np.empty_like(local)
    out[..., 0] = cn + c * local[..., 0] - s * local[..., 1]
    out[..., 1] = ce + s * local[..., 0] + c * local[..., 1]
    out[..., 2] = local[..., 2]
    return out


# Box corners: index = 4*top + 2*(y>0) + (x>0); sides and top only (the bottom is never seen). Winding does
# not matter: the renderer turns every normal to face the viewer.
_BOX_FACES = np.array([
    [4, 5, 7], [4, 7, 6],          # top (z = z_top, the upper face)
    [0, 1, 5], [0, 5, 4],          # y = -hy side
    [2, 6, 7], [2, 7, 3],          # y = +hy side
    [0, 4, 6], [0, 6, 2],          # x = -hx side
    [1, 3, 7], [1, 7, 5],          # x = +hx side
])


def boxes(cn, ce, hx, hy, yaw, z_bottom, z_top, material, tint, top_material=None, top_tint=None) -> Part:
    """Oriented boxes without a bottom face: half sizes hx (along yaw), hy; z_top < z_bottom (NED, up = -z).

    ``top_material`` / ``top_tint`` (optional) give the upper face its own material and tint (flat roofs).
    """
    cn = np.atleast_1d(np.asarray(cn, np.float64))
    k = cn.shape[0]
    hx, hy, zb, zt = (np.broadcast_to(np.asarray(a, np.float64), (k,)) for a in (hx, hy, z_bottom, z_top))
    corners = np.empty((k, 8, 3))
    for i in range(8):
        corners[:, i, 0] = np.where(i & 1, hx, -hx)
        corners[:, i, 1] = np.where(i & 2, hy, -hy)
        corners[:, i, 2] = np.where(i & 4, zt, zb)
    corners = _place(corners, cn, ce, np.broadcast_to(np.asarray(yaw, np.float64), (k,)))
    tris = corners[:, _BOX_FACES]                      # K×10×3×3
    part = _part(tris, material, np.broadcast_to(np.asarray(tint, np.float32), (k, 3)), len(_BOX_FACES))
    if top_material is not None:
        mat = part.material.reshape(k, -1)
        mat[:, :2] = np.asarray(top_material, np.uint8).reshape(-1, 1) if np.ndim(top_material) else top_material
    if top_tint is not None:
        part.tint.reshape(k, -1, 3)[:, :2] = np.broadcast_to(np.asarray(top_tint, np.float32), (k, 3))[:, None]
    return part


def gabled_roofs(cn, ce, hx, hy, yaw, z_eave, pitch_rad, roof_material, wall_material, roof_tint, wall_tint,
                 hip: np.ndarray | None = None) -> Part:
    """Gabled (or, where ``hip`` is true, hipped) roofs over oriented rectangles; ridge along local x.

    The roof overhangs nothing (eaves meet the walls) so the ground truth stays a clean polyhedron.
    """
    cn = np.atleast_1d(np.asarray(cn, np.float64))
    k = cn.shape[0]
    hx, hy, ze, pitch = (np.broadcast_to(np.asarray(a, np.float64), (k,)) for a in (hx, hy, z_eave, pitch_rad))
    hip = np.zeros(k, bool) if hip is None else np.broadcast_to(np.asarray(hip, bool), (k,))
    rise = hy * np.tan(pitch)
    inset = np.where(hip, np.minimum(hy, hx * 0.95), 0.0)     # hipped: ridge shortened by hy at each end
    zr = ze - rise
    # Points: 0..3 eave corners (-x-y, +x-y, +x+y, -x+y), 4/5 ridge ends (-x, +x).
    pts = np.zeros((k, 6, 3))
    pts[:, [0, 3], 0] = -hx[:, None]
    pts[:, [1, 2], 0] = hx[:, None]
    pts[:, [0, 1], 1] = -hy[:, None]
    pts[:, [2, 3], 1] = hy[:, None]
    pts[:, :4, 2] = ze[:, None]
    pts[:, 4, 0] = -hx + inset
    pts[:, 5, 0] = hx - inset
    pts[:, 4:, 2] = zr[:, None]
    pts = _place(pts, cn, ce, np.broadcast_to(np.asarray(yaw, np.float64), (k,)))
    slopes = pts[:, [[0, 1, 5], [0, 5, 4], [2, 3, 4], [2, 4, 5]]]          # two slope quads
    ends = pts[:, [[0, 4, 3], [1, 2, 5]]]                                   # gable (vertical) or hip (sloped)
    roof = _part(slopes, roof_material, np.broadcast_to(np.asarray(roof_tint, np.float32), (k, 3)), 4)
    end_mat = np.where(hip, roof_material, wall_material).astype(np.uint8)
    end_tint = np.where(hip[:, None], np.broadcast_to(np.asarray(roof_tint, np.float32), (k, 3)),
                        np.broadcast_to(np.asarray(wall_tint, np.float32), (k, 3)))
    return Part.concat([roof, _part(ends, end_mat, end_tint, 2)])


@lru_cache(maxsize=4)
def _unit_sphere(subdivisions: int) -> np.ndarray:
    """Icosphere triangles (T×3×3) on the unit sphere: an icosahedron, each face split in four per level."""
    g = (1.0 + 5 ** 0.5) / 2.0
    v = np.array([[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g], [0, -1, -g], [0, 1, -g],
                  [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]], np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                  [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                  [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    tris = v[f] / np.linalg.norm(v[f], axis=-1, keepdims=True)
    for _ in range(subdivisions):
        a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
        ab, bc, ca = [(x + y) / np.linalg.norm(x + y, axis=-1, keepdims=True) for x, y in ((a, b), (b, c), (c, a))]
        tris = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return tris


def ellipsoids(cn, ce, zc, rx, ry, rz, material, tint, subdivisions: int = 1) -> Part:
    """Low-poly ellipsoids (tree crowns, bushes) centred at (cn, ce, zc) with radii rx, ry, rz."""
    cn = np.atleast_1d(np.asarray(cn, np.float64))
    k = cn.shape[0]
    unit = _unit_sphere(subdivisions)
    radii = np.stack([np.broadcast_to(np.asarray(r, np.float64), (k,)) for r in (rx, ry, rz)], axis=1)
    centre = np.stack([cn, np.broadcast_to(np.asarray(ce, np.float64), (k,)),
                       np.broadcast_to(np.asarray(zc, np.float64), (k,))], axis=1)
    tris = unit[None] * radii[:, None, None, :] + centre[:, None, None, :]
    return _part(tris, material, np.broadcast_to(np.asarray(tint, np.float32), (k, 3)), unit.shape[0])


def cars(cn, ce, yaw, z_ground, body_material, glass_material, tint) -> Part:
    """Parked cars: a body box and a smaller cabin with a glass roof line, about 4.4 × 1.8 × 1.45 m."""
    cn = np.atleast_1d(np.asarray(cn, np.float64))
    k = cn.shape[0]
    zg = np.broadcast_to(np.asarray(z_ground, np.float64), (k,))
    yaw = np.broadcast_to(np.asarray(yaw, np.float64), (k,))
    body = boxes(cn, ce, 2.2, 0.9, yaw, zg + 0.3, zg - 0.85, body_material, tint)
    off = -0.25                                            # cabin sits slightly to the rear
    cab_n = cn + off * np.cos(yaw)
    cab_e = np.asarray(ce, np.float64) + off * np.sin(yaw)
    cabin = boxes(cab_n, cab_e, 1.15, 0.8, yaw, zg - 0.8, zg - 1.45, glass_material, np.full((k, 3), 0.5),
                  top_material=body_material, top_tint=tint)
    return Part.concat([body, cabin])
