"""Town layouts: where the roads, houses, towers, trees and cars go (suburban and urban styles).

Layouts loop over blocks and lots in Python but only collect numbers; the meshes are built in a few
vectorised calls at the end (see :mod:`sim.meshes`). Everything draws from the one seeded Generator.
"""
from __future__ import annotations

import math
from collections import defaultdict
from typing import cast

import numpy as np
import numpy.typing as npt

from .meshes import Part, boxes, cars, ellipsoids, gabled_roofs
from .world import WORLD_HALF_SIZE_M, GroundMap, Material, Terrain

ROOF_TINTS = np.array([[0.72, 0.33, 0.22], [0.35, 0.34, 0.36], [0.45, 0.30, 0.22], [0.30, 0.36, 0.45],
                       [0.55, 0.45, 0.38], [0.22, 0.22, 0.24]], np.float32)
WALL_TINTS = np.array([[0.92, 0.90, 0.85], [0.86, 0.78, 0.62], [0.78, 0.78, 0.76], [0.93, 0.86, 0.62],
                       [0.68, 0.38, 0.30], [0.80, 0.84, 0.88]], np.float32)
FACADE_TINTS = np.array([[0.70, 0.70, 0.70], [0.55, 0.62, 0.70], [0.80, 0.72, 0.58], [0.62, 0.40, 0.32],
                         [0.85, 0.85, 0.82], [0.45, 0.47, 0.50]], np.float32)
GLASS_TINTS = np.array([[0.55, 0.75, 0.95], [0.70, 0.80, 0.85], [0.50, 0.85, 0.80], [0.85, 0.80, 0.70]], np.float32)
FLAT_ROOF_TINTS = np.array([[0.55, 0.55, 0.53], [0.40, 0.40, 0.42], [0.70, 0.68, 0.64], [0.35, 0.40, 0.35]],
                           np.float32)
CAR_TINTS = np.array([[0.85, 0.85, 0.87], [0.10, 0.10, 0.12], [0.55, 0.56, 0.60], [0.65, 0.08, 0.07],
                      [0.10, 0.20, 0.50], [0.80, 0.80, 0.78], [0.20, 0.35, 0.22], [0.85, 0.65, 0.10]], np.float32)
FOLIAGE_TINTS = np.array([[0.85, 1.0, 0.80], [1.0, 1.0, 1.0], [0.75, 0.85, 0.65], [1.1, 1.0, 0.7]], np.float32)


class Collector:
    """Collects primitive parameters (one dict of lists per kind), then builds all meshes at once."""

    def __init__(self, rng: np.random.Generator, terrain: Terrain):
        self.rng, self.terrain = rng, terrain
        self.items: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
        self.spots: list[tuple[float, float]] = []

    def add(self, kind: str, **values) -> None:
        for k, v in values.items():
            self.items[kind][k].append(v)

    def ground_z(self, n: float, e: float, hx: float = 0.0, hy: float = 0.0) -> tuple[float, float]:
        """(z at the centre, lowest ground z under the footprint + 0.4 m): walls start below the ground."""
        z = [self.terrain.z_at_point(n + dn, e + de) for dn, de in ((0, 0), (-hx, -hy), (hx, -hy), (-hx, hy), (hx, hy))]
        return z[0], max(z) + 0.4

    def box(self, n, e, hx, hy, yaw, height, material, tint, top_material=None, z_ground=None, top_tint=None):
        """A box standing on the terrain (or on ``z_ground``, e.g. a roof); returns the z of its top."""
        zc, zb = self.ground_z(n, e, max(hx, hy), max(hx, hy))
        zg = zc if z_ground is None else z_ground
        self.add("box", n=n, e=e, hx=hx, hy=hy, yaw=yaw, zb=zb if z_ground is None else z_ground + 0.3,
                 zt=zg - height, mat=int(material), top=int(material if top_material is None else top_material),
                 tint=tint, top_tint=tint if top_tint is None else top_tint)
        return zg - height

    def tree(self, n, e, radius, scale=1.0):
        rng = self.rng
        zg, _ = self.ground_z(n, e)
        trunk_h = rng.uniform(1.8, 4.0) * scale
        rz = radius * rng.uniform(0.9, 1.4)
        self.add("box", n=n, e=e, hx=0.18 * scale, hy=0.18 * scale, yaw=rng.uniform(0, math.pi), zb=zg + 0.3,
                 zt=zg - trunk_h - 0.5 * rz, mat=int(Material.TRUNK), top=int(Material.TRUNK),
                 tint=np.ones(3, np.float32), top_tint=np.ones(3, np.float32))
        self.add("crown", n=n, e=e, z=zg - trunk_h - rz, rx=radius * rng.uniform(0.85, 1.15),
                 ry=radius * rng.uniform(0.85, 1.15), rz=rz, tint=FOLIAGE_TINTS[rng.integers(len(FOLIAGE_TINTS))])

    def car(self, n, e, yaw):
        zg, _ = self.ground_z(n, e)
        self.add("car", n=n, e=e, yaw=yaw, zg=zg, tint=CAR_TINTS[self.rng.integers(len(CAR_TINTS))])

    def build(self) -> Part:
        parts = []
        b = self.items.get("box")
        if b:
            a = {k: np.asarray(v) for k, v in b.items()}
            parts.append(boxes(a["n"], a["e"], a["hx"], a["hy"], a["yaw"], a["zb"], a["zt"], a["mat"], a["tint"],
                               top_material=a["top"], top_tint=a["top_tint"]))
        r = self.items.get("roof")
        if r:
            a = {k: np.asarray(v) for k, v in r.items()}
            parts.append(gabled_roofs(a["n"], a["e"], a["hx"], a["hy"], a["yaw"], a["z"], a["pitch"],
                                      Material.ROOF_TILE, Material.WALL, a["tint"], a["wall_tint"], hip=a["hip"]))
        c = self.items.get("crown")
        if c:
            a = {k: np.asarray(v) for k, v in c.items()}
            parts.append(ellipsoids(a["n"], a["e"], a["z"], a["rx"], a["ry"], a["rz"], Material.FOLIAGE, a["tint"]))
        k = self.items.get("car")
        if k:
            a = {k2: np.asarray(v) for k2, v in k.items()}
            parts.append(cars(a["n"], a["e"], a["yaw"], a["zg"], Material.CAR_PAINT, Material.GLASS, a["tint"]))
        return Part.concat(parts)


# (north0, east0, north1, east1) of axis-aligned rectangles, metres: scalars or arrays of corners. The casts
# below widen a union of two 4-tuples, which mypy cannot star-unpack before a fifth argument.
_Rect = tuple[npt.ArrayLike, npt.ArrayLike, npt.ArrayLike, npt.ArrayLike]


def _lines(rng, spacing_m: tuple[float, float]) -> np.ndarray:
    """Road centre lines across the world at random spacings (a little beyond the edges)."""
    out, x = [], -WORLD_HALF_SIZE_M - rng.uniform(0, spacing_m[1])
    while x < WORLD_HALF_SIZE_M + spacing_m[1]:
        out.append(x)
        x += rng.uniform(*spacing_m)
    return np.array(out)


def _paint_roads(ground: GroundMap, rng: np.random.Generator, avenues: np.ndarray, streets: np.ndarray,
                 half_width: float, sidewalk: float, urban: bool) -> None:
    """Sidewalks, asphalt, centre markings (and zebra crossings in town); avenues run north-south."""
    big = WORLD_HALF_SIZE_M + 50
    for lines, along_n in ((avenues, True), (streets, False)):
        for c in lines:
            lo, hi = (c - half_width - sidewalk, c + half_width + sidewalk)
            ground.rects(*cast(_Rect, (-big, lo, big, hi) if along_n else (lo, -big, hi, big)), Material.CONCRETE)
    for lines, along_n in ((avenues, True), (streets, False)):
        for c in lines:
            lo, hi = c - half_width, c + half_width
            ground.rects(*cast(_Rect, (-big, lo, big, hi) if along_n else (lo, -big, hi, big)), Material.ASPHALT)
    dash = np.arange(-big, big, 9.0)
    for lines, along_n in ((avenues, True), (streets, False)):
        for c in lines:
            offsets = (-half_width / 2, half_width / 2) if urban else (0.0,)
            for off in offsets:
                s0, s1 = dash, dash + 3.0
                w0, w1 = np.full_like(dash, c + off - 0.18), np.full_like(dash, c + off + 0.18)
                ground.rects(*cast(_Rect, (s0, w0, s1, w1) if along_n else (w0, s0, w1, s1)), Material.MARKING)
            if urban:       # solid double centre line
                for off in (-0.3, 0.3):
                    lo, hi = c + off - 0.12, c + off + 0.12
                    ground.rects(*cast(_Rect, (-big, lo, big, hi) if along_n else (lo, -big, hi, big)), Material.MARKING)
    for a in avenues:                           # clear the markings out of the intersections
        for s in streets:
            ground.rects(s - half_width, a - half_width, s + half_width, a + half_width, Material.ASPHALT)
            if urban:                           # zebra crossings on the four arms
                st = np.arange(-half_width + 0.5, half_width - 0.5, 1.2)
                for sign in (-1, 1):
                    n0 = s + sign * (half_width + 1.0)
                    ground.rects(np.full_like(st, min(n0, n0 + sign * 3)), a + st,
                                 np.full_like(st, max(n0, n0 + sign * 3)),
                                 a + st + 0.6, Material.MARKING)
                    e0 = a + sign * (half_width + 1.0)
                    ground.rects(s + st, np.full_like(st, min(e0, e0 + sign * 3)), s + st + 0.6,
                                 np.full_like(st, max(e0, e0 + sign * 3)), Material.MARKING)


def _house_lot(col: Collector, ground: GroundMap, n0: float, n1: float, front_e: float, direction: float,
               depth: float) -> None:
    """One suburban lot: lot spans north [n0, n1] and east from front_e inward by ``depth`` (direction ±1)."""
    rng = col.rng
    width = n1 - n0

    def to_e(v):
        return front_e + direction * v

    house_u = rng.uniform(9.0, min(15.0, width - 5.0))
    house_v = rng.uniform(8.0, min(13.0, depth - 12.0))
    setback = rng.uniform(5.0, 8.5)
    side = rng.choice([-1.0, 1.0])
    garage = rng.random() < 0.4
    free_u = width - house_u - (6.5 if garage else 3.8)
    u_house = (n0 + n1) / 2 - side * max(free_u, 0.0) / 2 * rng.uniform(0.3, 1.0)
    v_house = setback + house_v / 2
    cn, ce = u_house, to_e(v_house)
    along_n = house_u >= house_v
    hx, hy, yaw = (house_u / 2, house_v / 2, 0.0) if along_n else (house_v / 2, house_u / 2, math.pi / 2)
    wall_h = rng.choice([2.9, 3.2, 5.6, 6.0]) + rng.uniform(-0.2, 0.2)
    wall_tint = WALL_TINTS[rng.integers(len(WALL_TINTS))]
    z_eave = col.box(cn, ce, hx, hy, yaw, wall_h, Material.WALL, wall_tint)
    col.add("roof", n=cn, e=ce, hx=hx, hy=hy, yaw=yaw, z=z_eave, pitch=math.radians(rng.uniform(22, 40)),
            tint=ROOF_TINTS[rng.integers(len(ROOF_TINTS))] * rng.uniform(0.85, 1.1), wall_tint=wall_tint,
            hip=bool(rng.random() < 0.45))
    edge_u = u_house + side * house_u / 2                 # the house's side facing the driveway
    if garage:
        g_u = edge_u + side * 3.2
        col.box(g_u, to_e(setback + 3.2), 3.0, 3.0, 0.0, 3.0, Material.WALL, wall_tint, top_material=Material.ROOF_FLAT,
                top_tint=FLAT_ROOF_TINTS[0])
        d0, d1, d_end = g_u - 2.6, g_u + 2.6, setback + 0.2
    else:
        d0, d1 = sorted((edge_u + side * 0.5, edge_u + side * 3.8))
        d_end = setback + house_v * 0.8
    ground.rects(d0, min(to_e(0), to_e(d_end)), d1, max(to_e(0), to_e(d_end)), Material.CONCRETE)
    if rng.random() < 0.6:
        col.car((d0 + d1) / 2, to_e(rng.uniform(2.8, max(d_end - 2.4, 3.0))),
                direction * math.pi / 2 + rng.normal(0, 0.04))
    if rng.random() < 0.5:                                 # front walkway
        ground.rects(u_house - 0.6, min(to_e(0), to_e(setback)), u_house + 0.6, max(to_e(0), to_e(setback)),
                     Material.CONCRETE)
    back0 = setback + house_v + 2.0
    for _ in range(rng.integers(0, 4)):                    # backyard trees
        if depth - 2.0 > back0:
            col.tree(rng.uniform(n0 + 2, n1 - 2), to_e(rng.uniform(back0, depth - 2.0)), rng.uniform(2.0, 4.5))
    for _ in range(rng.integers(0, 3)):                    # bushes by the house front
        col.add("crown", n=u_house + rng.uniform(-hx, hx), e=to_e(setback - 1.0),
                z=col.ground_z(u_house, to_e(setback))[0] - 0.5,
                rx=rng.uniform(0.6, 1.2), ry=rng.uniform(0.6, 1.2), rz=rng.uniform(0.5, 0.9), tint=FOLIAGE_TINTS[0])
    if rng.random() < 0.3:                                 # hedge along the back of the lot
        v = depth - 0.8
        col.box((n0 + n1) / 2, to_e(v), width / 2 - 0.5, 0.5, 0.0, rng.uniform(1.2, 2.0), Material.FOLIAGE,
                FOLIAGE_TINTS[2])
    if rng.random() < 0.08 and depth - back0 > 6:          # a garden shed or a pool deck
        col.box(rng.uniform(n0 + 3, n1 - 3), to_e(depth - 3.5), 1.5, 1.2, 0.0, 2.3, Material.WALL, WALL_TINTS[2],
                top_material=Material.ROOF_FLAT, top_tint=FLAT_ROOF_TINTS[1])
    elif depth - back0 > 12 and rng.random() < 0.15:       # a garden pool with a paved deck
        u, v = rng.uniform(n0 + 5, n1 - 5), back0 + 4.0
        ground.rects(u - 4.5, min(to_e(v - 2.8), to_e(v + 2.8)), u + 4.5, max(to_e(v - 2.8), to_e(v + 2.8)),
                     Material.CONCRETE)
        ground.rects(u - 3.5, min(to_e(v - 1.8), to_e(v + 1.8)), u + 3.5, max(to_e(v - 1.8), to_e(v + 1.8)),
                     Material.WATER)
    elif depth - back0 > 8:
        col.spots.append(((n0 + n1) / 2, to_e((back0 + depth) / 2)))


def suburban_layout(rng: np.random.Generator, terrain: Terrain, ground: GroundMap) -> tuple[Part, np.ndarray]:
    col = Collector(rng, terrain)
    avenues, streets = _lines(rng, (95.0, 125.0)), _lines(rng, (170.0, 240.0))
    half_w, sidewalk, verge = 4.5, 1.8, 2.5
    _paint_roads(ground, rng, avenues, streets, half_w, sidewalk, urban=False)
    for ea, eb in zip(avenues[:-1], avenues[1:]):
        for na, nb in zip(streets[:-1], streets[1:]):
            e_in0, e_in1 = ea + half_w + sidewalk, eb - half_w - sidewalk
            n_in0, n_in1 = na + half_w + sidewalk + verge, nb - half_w - sidewalk - verge
            if rng.random() < 0.1:                         # a park
                for _ in range(rng.integers(8, 30)):
                    col.tree(rng.uniform(n_in0 + 3, n_in1 - 3), rng.uniform(e_in0 + 3, e_in1 - 3),
                             rng.uniform(2.5, 5.0))
                mid = (e_in0 + e_in1) / 2
                ground.rects(n_in0, mid - 1.2, n_in1, mid + 1.2, Material.SOIL)
                col.spots += [(rng.uniform(n_in0 + 10, n_in1 - 10), rng.uniform(e_in0 + 10, e_in1 - 10))
                              for _ in range(4)]
                continue
            depth = (e_in1 - e_in0) / 2 - verge
            for front, direction in ((e_in0 + verge, 1.0), (e_in1 - verge, -1.0)):
                n = n_in0
                while n_in1 - n > 18.0:
                    w = rng.uniform(18.0, 28.0)
                    w = n_in1 - n if n_in1 - n - w < 18.0 else w
                    _house_lot(col, ground, n, n + w, front, direction, depth)
                    if rng.random() < 0.5:                 # street tree in the verge
                        col.tree(n + rng.uniform(2, w - 2), front - direction * verge / 2, rng.uniform(2.0, 3.5))
                    if rng.random() < 0.25:                # car parked at the kerb
                        curb = (ea + half_w - 1.2) if direction > 0 else (eb - half_w + 1.2)
                        col.car(n + rng.uniform(3, w - 3), curb, rng.choice([0.0, math.pi]) + rng.normal(0, 0.03))
                    n += w
    return col.build(), np.array(col.spots).reshape(-1, 2)


def _urban_block(col: Collector, ground: GroundMap, n0, e0, n1, e1) -> None:
    rng = col.rng
    kind = rng.random()
    if kind < 0.10:                                        # plaza: paving, trees in rows, kiosks
        ground.rects(n0, e0, n1, e1, Material.PAVING)
        for n in np.arange(n0 + 6, n1 - 5, rng.uniform(9, 14)):
            for e in (e0 + 5, e1 - 5):
                col.tree(n, e, rng.uniform(2.0, 3.2))
        for _ in range(rng.integers(0, 3)):
            col.box(rng.uniform(n0 + 8, n1 - 8), rng.uniform(e0 + 12, e1 - 12), rng.uniform(1.5, 3),
                    rng.uniform(1.5, 3),
                    0.0, rng.uniform(2.5, 3.5), Material.CLUTTER, FACADE_TINTS[rng.integers(6)], Material.ROOF_FLAT,
                    top_tint=FLAT_ROOF_TINTS[2])
        col.spots += [((n0 + n1) / 2 + rng.uniform(-5, 5), (e0 + e1) / 2 + rng.uniform(-5, 5))]
        return
    if kind < 0.17:                                        # small park
        ground.rects(n0, e0, n1, e1, Material.GRASS)
        ground.rects(n0, (e0 + e1) / 2 - 1.5, n1, (e0 + e1) / 2 + 1.5, Material.PAVING)
        for _ in range(rng.integers(10, 35)):
            col.tree(rng.uniform(n0 + 3, n1 - 3), rng.uniform(e0 + 3, e1 - 3), rng.uniform(2.5, 4.5))
        col.spots += [((n0 + n1) / 2, (e0 + e1) / 2)]
        return
    cuts_n = np.sort(np.concatenate([[n0, n1], rng.uniform(n0 + 15, n1 - 15, rng.integers(0, 3))]))
    cuts_e = np.sort(np.concatenate([[e0, e1], rng.uniform(e0 + 15, e1 - 15, rng.integers(0, 2))]))
    for pa, pb in zip(cuts_n[:-1], cuts_n[1:]):
        for qa, qb in zip(cuts_e[:-1], cuts_e[1:]):
            if pb - pa < 6 or qb - qa < 6:
                continue
            m = rng.choice([0.0, 0.0, 0.5, 1.5])
            hx, hy = (pb - pa) / 2 - m, (qb - qa) / 2 - m
            cn, ce = (pa + pb) / 2, (qa + qb) / 2
            height = float(np.clip(rng.lognormal(math.log(20.0), 0.6), 6.0, 95.0))
            tint = FACADE_TINTS[rng.integers(len(FACADE_TINTS))] * rng.uniform(0.85, 1.1)
            roof_tint = FLAT_ROOF_TINTS[rng.integers(len(FLAT_ROOF_TINTS))]
            wall = Material.CURTAIN_WALL if height > 20 and rng.random() < 0.35 else Material.FACADE
            if wall is Material.CURTAIN_WALL:
                tint = GLASS_TINTS[rng.integers(len(GLASS_TINTS))]
            z_roof = col.box(cn, ce, hx, hy, 0.0, height, wall, tint, Material.ROOF_FLAT, top_tint=roof_tint)
            if height > 25 and rng.random() < 0.35:    # a setback tower on top
                f = rng.uniform(0.55, 0.8)
                z_roof = col.box(cn, ce, hx * f, hy * f, 0.0, rng.uniform(5, 30), wall, tint,
                                 Material.ROOF_FLAT, z_ground=z_roof, top_tint=roof_tint)
                hx, hy = hx * f, hy * f
            for _ in range(rng.integers(0, 6)):         # roof clutter: plant rooms, AC units
                if hx > 4 and hy > 4:
                    col.box(cn + rng.uniform(-hx + 2.5, hx - 2.5), ce + rng.uniform(-hy + 2.5, hy - 2.5),
                            rng.uniform(0.5, 2.0), rng.uniform(0.5, 2.0), 0.0, rng.uniform(0.8, 3.0), Material.CLUTTER,
                            roof_tint * 1.2, Material.CLUTTER, z_ground=z_roof)


def urban_layout(rng: np.random.Generator, terrain: Terrain, ground: GroundMap) -> tuple[Part, np.ndarray]:
    col = Collector(rng, terrain)
    avenues, streets = _lines(rng, (80.0, 120.0)), _lines(rng, (70.0, 110.0))
    half_w, sidewalk = 8.0, 4.0
    _paint_roads(ground, rng, avenues, streets, half_w, sidewalk, urban=True)
    for ea, eb in zip(avenues[:-1], avenues[1:]):
        for na, nb in zip(streets[:-1], streets[1:]):
            n0, n1 = na + half_w + sidewalk, nb - half_w - sidewalk
            e0, e1 = ea + half_w + sidewalk, eb - half_w - sidewalk
            _urban_block(col, ground, n0, e0, n1, e1)
            for n in np.arange(n0 + 5, n1 - 5, 12.0):      # street trees and kerbside cars along the avenues
                for e_tree, e_car, yaw in ((e0 - 1.5, ea + half_w - 1.3, 0.0), (e1 + 1.5, eb - half_w + 1.3, math.pi)):
                    if rng.random() < 0.35:
                        col.tree(n + rng.uniform(-1, 1), e_tree, rng.uniform(1.8, 3.0))
                    for dn in (0.0, 6.0):
                        if rng.random() < 0.45:
                            col.car(n + dn, e_car, yaw + rng.normal(0, 0.03))
            for e in np.arange(e0 + 5, e1 - 5, 6.5):        # kerbside cars along the streets
                for n_car, yaw in ((na + half_w - 1.3, math.pi / 2), (nb - half_w + 1.3, -math.pi / 2)):
                    if rng.random() < 0.4:
                        col.car(n_car, e, yaw + rng.normal(0, 0.03))
    return col.build(), np.array(col.spots).reshape(-1, 2)
