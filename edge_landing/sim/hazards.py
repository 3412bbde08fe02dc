"""Hazards inside the open areas: what a drone must not land on, placed around the towns' landing spots.

Without these, most of what a camera sees in the open areas is flat ground and a network that says "all
horizontal" is nearly right (73–80 % of labelled pixels are horizontal in the plain towns). Around every
landing spot (parks, backyards, plazas) a seeded mix is placed in a ring between ``keep_clear_m`` and
``ring_m``: parked cars, bushes and trees of several sizes, low walls, poles, and clutter boxes (crates,
kiosks, roof-unit sized boxes). The spot itself stays open (flights pick spots clear within 5 m), so a
landing is still possible, next to things that stick out by 0.5–10 m. Uses its own Generator (seeded from
the world's seed), so the town's layout is the same with or without hazards.

People (``people_part``, opt-in) stand around the same spots: 0.45 × 0.28 m across and 1.5-1.9 m tall, a
pixel or two wide to a 640-pixel camera 40 m up, which is what makes them the hardest hazard for motion
geometry (docs/MEASUREMENTS.md, "Narrow obstacles").
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from .meshes import Part
from .towns import FOLIAGE_TINTS, Collector
from .world import Material, Terrain

WALL_TINT = np.array([0.72, 0.70, 0.66], np.float32)
POLE_TINT = np.array([0.45, 0.45, 0.47], np.float32)
CLUTTER_TINTS = np.array([[0.60, 0.55, 0.45], [0.35, 0.38, 0.40], [0.75, 0.72, 0.68]], np.float32)
CLOTHING_TINTS = np.array([[0.15, 0.18, 0.35], [0.55, 0.12, 0.10], [0.80, 0.78, 0.70], [0.20, 0.20, 0.20],
                           [0.30, 0.45, 0.25]], np.float32)


@dataclass(frozen=True)
class HazardConfig:
    """Metres; ``per_spot`` hazards around every landing spot."""

    per_spot: int = 25
    keep_clear_m: float = 7.0     # nothing closer to the spot's centre than this (its 5 m disc stays open)
    ring_m: float = 30.0          # ... nor farther than this


@dataclass(frozen=True)
class PeopleConfig:
    """Metres; ``per_spot`` people standing around every landing spot, its open disc included (people walk into
    the places a drone would land: the flight must find a spot without them)."""

    per_spot: int = 6
    keep_clear_m: float = 0.0
    ring_m: float = 20.0
    half_width_m: tuple[float, float] = (0.225, 0.14)   # shoulders by chest, halved
    height_m: tuple[float, float] = (1.5, 1.9)


def hazard_part(rng: np.random.Generator, terrain: Terrain, spots: np.ndarray,
                config: HazardConfig = HazardConfig()) -> Part:
    """Meshes of the hazards around ``spots`` (N×2 north, east), standing on ``terrain``."""
    col = Collector(rng, terrain)
    for n, e, bearing in _around(rng, spots, config.per_spot, config.keep_clear_m, config.ring_m):
        _one(col, rng, n, e, bearing)
    return col.build()


def _around(rng: np.random.Generator, spots: np.ndarray, per_spot: int, keep_clear_m: float,
            ring_m: float) -> Iterator[tuple[float, float, float]]:
    """(north, east, bearing from the spot) of ``per_spot`` places per spot, uniform over the ring between
    ``keep_clear_m`` and ``ring_m``; drawn lazily, so what the caller draws for each place comes in between."""
    for n0, e0 in np.asarray(spots, np.float64).reshape(-1, 2):
        for _ in range(per_spot):
            r = math.sqrt(rng.uniform(keep_clear_m ** 2, ring_m ** 2))
            a = rng.uniform(0.0, 2.0 * math.pi)
            yield n0 + r * math.cos(a), e0 + r * math.sin(a), a


def _one(col: Collector, rng: np.random.Generator, n: float, e: float, bearing: float) -> None:
    kind = rng.random()
    yaw = rng.uniform(0.0, math.pi)
    if kind < 0.30:                                           # parked car (1.5 m)
        col.car(n, e, yaw)
    elif kind < 0.50:                                         # bush, 0.6-1.8 m tall
        zg, _ = col.ground_z(n, e)
        rz = rng.uniform(0.3, 0.9)
        col.add("crown", n=n, e=e, z=zg - rz, rx=rng.uniform(0.6, 1.6), ry=rng.uniform(0.6, 1.6), rz=rz,
                tint=FOLIAGE_TINTS[rng.integers(len(FOLIAGE_TINTS))])
    elif kind < 0.65:                                         # tree, small to large
        col.tree(n, e, rng.uniform(1.0, 4.0), scale=rng.uniform(0.5, 1.2))
    elif kind < 0.80:                                         # low wall / fence run, tangential to the spot
        col.box(n, e, rng.uniform(2.0, 6.0), 0.12, bearing + math.pi / 2, rng.uniform(0.6, 1.5), Material.WALL,
                WALL_TINT, top_material=Material.CONCRETE)
    elif kind < 0.90:                                         # pole / lamp post, 3-9 m
        col.box(n, e, 0.12, 0.12, yaw, rng.uniform(3.0, 9.0), Material.TRUNK, POLE_TINT)
    else:                                                     # clutter: crates, kiosks, roof-unit boxes
        col.box(n, e, rng.uniform(0.5, 2.0), rng.uniform(0.5, 2.0), yaw, rng.uniform(0.5, 2.5), Material.CLUTTER,
                CLUTTER_TINTS[rng.integers(len(CLUTTER_TINTS))])


def people_part(rng: np.random.Generator, terrain: Terrain, spots: np.ndarray,
                config: PeopleConfig = PeopleConfig()) -> Part:
    """People standing around ``spots`` (N×2 north, east) on ``terrain``: one box each, in clothing colours."""
    col = Collector(rng, terrain)
    hx, hy = config.half_width_m
    for n, e, _ in _around(rng, spots, config.per_spot, config.keep_clear_m, config.ring_m):
        col.box(n, e, hx, hy, rng.uniform(0.0, math.pi), rng.uniform(*config.height_m), Material.CLUTTER,
                CLOTHING_TINTS[rng.integers(len(CLOTHING_TINTS))])
    return col.build()
