"""Hand-built worlds whose truth is known by construction: a flat grass field with boxes standing on it.

Used where a generated town would hide the question asked (how high does motion geometry read a box of this
size from that height?): tests/test_motion.py and benchmarks/narrow_obstacles.py. World frame = local NED,
ground at down = 0.
"""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from .effects import EffectOverrides, Effects, sample_effects
from .meshes import boxes
from .world import WORLD_HALF_SIZE_M, GroundMap, Material, Style, Terrain, World, _finish

__all__ = ["flat_field", "quiet_effects"]


def flat_field(box_rows: Sequence[Sequence[float]], seed: int = 0, side: Material = Material.CAR_PAINT,
               tint: Sequence[float] = (0.6, 0.2, 0.2), top: Material = Material.GRASS,
               style: Optional[Style] = None) -> World:
    """A flat grass field (down = 0) with boxes given as rows (north, east, half_n, half_e, height_m): ``side``
    material and ``tint`` on their sides, ``top`` on their tops (grass by default). Tops are textured on
    purpose: flow cannot measure a textureless surface (it fills it in from around it)."""
    n = int(round(2 * WORLD_HALF_SIZE_M / 10.0)) + 1
    terrain = Terrain(z=np.zeros((n, n)), origin_m=-WORLD_HALF_SIZE_M, step_m=10.0)
    b = np.asarray(box_rows, np.float64).reshape(-1, 5)
    part = boxes(b[:, 0], b[:, 1], b[:, 2], b[:, 3], 0.0, 0.3, -b[:, 4], side, np.array(tint, np.float32),
                 top_material=top)
    return _finish(style or Style.SUBURBAN, seed, part, terrain, GroundMap(Material.GRASS), np.zeros((0, 2)))


def quiet_effects() -> Effects:
    """The camera effects a hand-built field is seen with: no haze, rain, blur or exposure change; sensor noise
    0.01 (the question asked is geometry's, not the weather's)."""
    return sample_effects(np.random.default_rng(0), EffectOverrides(haze_per_m=0.0, rain=0.0, motion_blur_px=0.0,
                                                                    noise_sigma=0.01, exposure_ev=0.0))
