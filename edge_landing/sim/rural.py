"""The rural/industrial world style: the held-out zero-shot test (never in training, like the paper's AirSimNC).

Unlike the two towns: no street grid, large fields (bare soil, grass, crop rows), dirt tracks along field
edges, one paved road, farmyards and industrial yards of concrete with sheds, halls and shipping containers
(some stacked), ponds and a canal, hedgerows and small woods. Built from the same primitives as the towns
(:class:`towns.Collector`), so only the layout differs, not the renderer.
"""
from __future__ import annotations

import math

import numpy as np

from .meshes import Part
from .towns import FLAT_ROOF_TINTS, ROOF_TINTS, WALL_TINTS, Collector
from .world import WORLD_HALF_SIZE_M, GroundMap, Material, Terrain

CONTAINER_TINTS = np.array([[0.70, 0.20, 0.15], [0.15, 0.35, 0.60], [0.20, 0.45, 0.25], [0.85, 0.55, 0.10],
                            [0.55, 0.55, 0.55], [0.85, 0.85, 0.82], [0.40, 0.25, 0.15]], np.float32)
_FIELD_MATERIALS = (Material.SOIL, Material.GRASS, Material.GRASS, Material.SOIL)


def _edges(rng: np.random.Generator, lo: float, hi: float, size_m: tuple[float, float]) -> np.ndarray:
    out, x = [lo], lo
    while x < hi:
        x += rng.uniform(*size_m)
        out.append(min(x, hi))
    return np.array(out)


def _field(ground: GroundMap, rng: np.random.Generator, n0: float, e0: float, n1: float, e1: float) -> None:
    """One field: plain soil or grass, or crop rows (stripes of soil and grass) in one direction."""
    base = _FIELD_MATERIALS[rng.integers(len(_FIELD_MATERIALS))]
    ground.rects(n0, e0, n1, e1, base)
    if rng.random() < 0.45:
        pitch = rng.uniform(0.8, 2.5)
        width = pitch * rng.uniform(0.3, 0.6)
        other = Material.GRASS if base is Material.SOIL else Material.SOIL
        if rng.random() < 0.5:
            s = np.arange(n0, n1 - width, pitch)
            ground.rects(s, np.full_like(s, e0), s + width, np.full_like(s, e1), other)
        else:
            s = np.arange(e0, e1 - width, pitch)
            ground.rects(np.full_like(s, n0), s, np.full_like(s, n1), s + width, other)


def _yard(col: Collector, ground: GroundMap, n: float, e: float, industrial: bool) -> None:
    """A concrete yard with sheds or halls, containers (some stacked) and a few vehicles."""
    rng = col.rng
    hn, he = rng.uniform(25, 60), rng.uniform(25, 60)
    ground.rects(n - hn, e - he, n + hn, e + he, Material.CONCRETE)
    for _ in range(rng.integers(2, 6)):                          # sheds / halls
        bx, by = rng.uniform(5, 18 if industrial else 10), rng.uniform(4, 12)
        cn, ce = n + rng.uniform(-hn + bx, hn - bx), e + rng.uniform(-he + by, he - by)
        height = rng.uniform(4, 10 if industrial else 6)
        wall = WALL_TINTS[rng.integers(len(WALL_TINTS))]
        if rng.random() < 0.5:
            z = col.box(cn, ce, bx, by, 0.0, height, Material.WALL, wall, Material.ROOF_FLAT,
                        top_tint=FLAT_ROOF_TINTS[rng.integers(len(FLAT_ROOF_TINTS))])
        else:
            z = col.box(cn, ce, bx, by, 0.0, height, Material.WALL, wall)
            col.add("roof", n=cn, e=ce, hx=bx, hy=by, yaw=0.0, z=z, pitch=math.radians(rng.uniform(10, 25)),
                    tint=ROOF_TINTS[rng.integers(len(ROOF_TINTS))], wall_tint=wall, hip=False)
    for _ in range(rng.integers(6, 30 if industrial else 10)):   # containers: 6.1 or 12.2 x 2.4 x 2.6 m
        length = 6.1 if rng.random() < 0.5 else 12.2
        yaw = rng.choice([0.0, math.pi / 2]) + rng.normal(0, 0.02)
        cn, ce = n + rng.uniform(-hn + 7, hn - 7), e + rng.uniform(-he + 7, he - 7)
        tint = CONTAINER_TINTS[rng.integers(len(CONTAINER_TINTS))]
        z = col.box(cn, ce, length / 2, 1.22, yaw, 2.6, Material.CLUTTER, tint)
        if industrial and rng.random() < 0.35:
            col.box(cn, ce, length / 2, 1.22, yaw, 2.6, Material.CLUTTER,
                    CONTAINER_TINTS[rng.integers(len(CONTAINER_TINTS))], z_ground=z)
    for _ in range(rng.integers(0, 4)):
        col.car(n + rng.uniform(-hn + 3, hn - 3), e + rng.uniform(-he + 3, he - 3), rng.uniform(0, math.pi))
    col.spots.append((n + rng.uniform(-hn, hn) * 0.5, e + rng.uniform(-he, he) * 0.5))


def rural_layout(rng: np.random.Generator, terrain: Terrain, ground: GroundMap) -> tuple[Part, np.ndarray]:
    col = Collector(rng, terrain)
    big = WORLD_HALF_SIZE_M
    ns = _edges(rng, -big, big, (50.0, 160.0))
    es = _edges(rng, -big, big, (50.0, 160.0))
    for na, nb in zip(ns[:-1], ns[1:]):
        for ea, eb in zip(es[:-1], es[1:]):
            _field(ground, rng, na, ea, nb, eb)
            col.spots.append(((na + nb) / 2, (ea + eb) / 2))
    track_w = rng.uniform(2.5, 4.0)
    for c in ns[1:-1]:                                            # dirt tracks and hedgerows on field edges
        if rng.random() < 0.5:
            ground.rects(c - track_w / 2, -big, c + track_w / 2, big, Material.SOIL)
        if rng.random() < 0.7:                                    # hedgerow trees (only near the centre)
            for e in np.arange(-250, 250, rng.uniform(5, 10)):
                if abs(c) < 250 and rng.random() < 0.75:
                    col.tree(c + track_w + rng.uniform(-1, 1), e + rng.uniform(-2, 2), rng.uniform(1.5, 4.0))
    for c in es[1:-1]:
        if rng.random() < 0.4:
            ground.rects(-big, c - track_w / 2, big, c + track_w / 2, Material.SOIL)
    road = rng.uniform(-100, 100)                                  # one paved road, east-west
    ground.rects(road - 3.5, -big, road + 3.5, big, Material.ASPHALT)
    dash = np.arange(-big, big, 12.0)
    ground.rects(np.full_like(dash, road - 0.1), dash, np.full_like(dash, road + 0.1), dash + 4.0, Material.MARKING)
    canal = rng.uniform(-150, 150)                                 # a canal with soil banks, north-south
    ground.rects(-big, canal - 7, big, canal + 7, Material.SOIL)
    ground.rects(-big, canal - 5, big, canal + 5, Material.WATER)
    for _ in range(rng.integers(3, 8)):                            # ponds
        n, e = rng.uniform(-200, 200, 2)
        rn, re = rng.uniform(6, 25, 2)
        for k in range(6):                                         # a rounded pond from stacked rectangles
            f = math.cos(math.pi * k / 12)
            ground.rects(n - rn * f, e - re * math.sin(math.pi * (k + 6) / 12), n + rn * f,
                         e + re * math.sin(math.pi * (k + 6) / 12), Material.WATER)
    for _ in range(rng.integers(5, 10)):                           # small woods
        n, e, r = rng.uniform(-220, 220), rng.uniform(-220, 220), rng.uniform(15, 40)
        for _ in range(int(r * rng.uniform(0.8, 1.5))):
            a, d = rng.uniform(0, 2 * math.pi), r * math.sqrt(rng.random())
            col.tree(n + d * math.cos(a), e + d * math.sin(a), rng.uniform(2.5, 5.0))
    for _ in range(rng.integers(3, 7)):                            # orchards: trees in rows
        n, e = rng.uniform(-200, 200, 2)
        for dn in np.arange(-30, 30, rng.uniform(5, 8)):
            for de in np.arange(-40, 40, rng.uniform(4, 6)):
                col.tree(n + dn, e + de, rng.uniform(1.2, 2.2), scale=0.6)
    for i in range(rng.integers(10, 18)):                          # farmyards and industrial yards
        n, e = rng.uniform(-200, 200, 2)
        _yard(col, ground, n, e, industrial=i % 2 == 0)
    for _ in range(rng.integers(4, 12)):                           # traffic on the road
        col.car(road + rng.choice([-1.7, 1.7]), rng.uniform(-200, 200), rng.choice([math.pi / 2, -math.pi / 2]))
    return col.build(), np.array(col.spots).reshape(-1, 2)
