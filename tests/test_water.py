"""Still water (sim.water): rendered as a camera sees it, read by motion geometry as what it is, not level ground.

The pool worlds are real sim worlds (Embree ray casting, the sim's textures and sensor effects); only their
layout is written here so that the truth is known.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from edge_landing.runtime.core.camera import Mount
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
from edge_landing.runtime.fusion.motion import CameraPose, MotionConfig, MotionStage

sim = pytest.importorskip("edge_landing.sim", reason="the sim extra (embreex) renders the test worlds")
from edge_landing.benchmarks.landing_truth import TruthConfig, check_target  # noqa: E402
from edge_landing.benchmarks.lying_model import lying_prediction  # noqa: E402
from edge_landing.sim.meshes import boxes  # noqa: E402
from edge_landing.sim.water import NORMAL_REFLECTANCE, WATER_INDEX, floor_points, fresnel  # noqa: E402
from edge_landing.sim.world import WORLD_HALF_SIZE_M, GroundMap, Material, Terrain, _finish  # noqa: E402

from .test_motion import INTR, _frames  # noqa: E402

UP = np.array([[0.0, 0.0, -1.0]])          # a level surface's normal, facing a camera above it (NED)
FLOOR_DEPTH_M = 1.5


def test_a_vertical_ray_goes_straight_down_to_the_floor():
    pts, path = floor_points(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), UP, FLOOR_DEPTH_M)
    np.testing.assert_allclose(pts, [[0.0, 0.0, FLOOR_DEPTH_M]], atol=1e-9)
    assert path[0] == pytest.approx(FLOOR_DEPTH_M)


def test_an_oblique_ray_bends_towards_the_normal_by_snells_law():
    incidence = math.radians(50.0)
    d = np.array([[math.sin(incidence), 0.0, math.cos(incidence)]])
    pts, _ = floor_points(np.zeros((1, 3)), d, UP, FLOOR_DEPTH_M)
    refracted = math.atan2(pts[0, 0], pts[0, 2])
    assert math.sin(incidence) == pytest.approx(WATER_INDEX * math.sin(refracted))
    assert pts[0, 2] == pytest.approx(FLOOR_DEPTH_M)
    assert pts[0, 0] < FLOOR_DEPTH_M * math.tan(incidence)   # nearer than the straight ray would reach


def test_fresnel_reflects_little_from_above_and_most_at_grazing_angles():
    r = fresnel(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.02]]), np.repeat(UP, 2, axis=0))
    assert r[0] == pytest.approx(NORMAL_REFLECTANCE)
    assert r[1] > 0.9


def _water_world(pools: list[tuple[float, float, float, float]], style=None):
    """A flat grass field (down = 0) with water rectangles (north, east, half north, half east); the world's
    style picks the water (sim.water.water_of): clear garden pools in the towns, murky ponds in the country."""
    n = int(round(2 * WORLD_HALF_SIZE_M / 10.0)) + 1
    terrain = Terrain(z=np.zeros((n, n)), origin_m=-WORLD_HALF_SIZE_M, step_m=10.0)
    ground = GroundMap(Material.GRASS)
    for pn, pe, hn, he in pools:
        ground.rects(pn - hn, pe - he, pn + hn, pe + he, Material.WATER)
    nothing = boxes(np.zeros(0), np.zeros(0), 0.0, 0.0, 0.0, 0.3, 0.0, Material.CAR_PAINT,
                    np.array((0.5, 0.5, 0.5), np.float32))
    return _finish(style or sim.Style.SUBURBAN, 0, nothing, terrain, ground, np.zeros((0, 2)))


def test_geometry_reads_a_clear_pool_below_the_ground_not_level_with_it():
    """The floor seen through the water moves like ground about a metre down: parallax says so, as it would
    over a real pool (a texture painted on the surface would read as level ground)."""
    pool_n, pool_e = 40.0, 0.0
    world = _water_world([(pool_n, pool_e, 6.0, 6.0)])
    stage = MotionStage(MotionConfig(), INTR, Mount())
    result, render = None, None
    for _k, t, r, state in _frames(world, [(0.0, -6.0, -40.0), (0.0, 6.0, -40.0)]):
        pose = CameraPose.of(Mount(), state.attitude, state.position_ned_m, state.agl_m)
        result = stage.update(r.rgb, pose, t, focus_ned_m=np.array([pool_n, pool_e, 0.0]))
        render = r
    assert result is not None
    mat = render.geometry.material[result.rows, result.cols]
    pts = render.geometry.points_ned[result.rows, result.cols]
    inner = (mat == Material.WATER) & (np.abs(pts[..., 0] - pool_n) < 4.0) & (np.abs(pts[..., 1] - pool_e) < 4.0)
    h_pool = result.height_m[inner & np.isfinite(result.height_m)]
    grass = (mat == Material.GRASS) & (np.hypot(pts[..., 0] - pool_n, pts[..., 1] - pool_e) > 10.0)
    h_grass = result.height_m[grass & np.isfinite(result.height_m)]
    assert h_pool.size > 20 and h_grass.size > 100
    assert float(np.median(h_pool)) < -0.5, np.median(h_pool)           # below the plane by more than 0.5 m
    assert abs(float(np.median(h_grass))) < 0.2


def _liar_over(world, path) -> tuple[int, int]:
    """(geometry-confirmed targets, the liar's own targets on water) along ``path``; asserts that every confirmed
    target is safe by ray casting (water unsafe)."""
    truth = TruthConfig(log="", clearance_m=FusionConfig().required_clearance_m)
    geo = LandingFuser(FusionConfig(), INTR, Mount())
    liar = LandingFuser(FusionConfig(allow_unconfirmed=True), INTR, Mount())

    def safe(k, target):
        ok, why = check_target(world, *target.position_ned_m[:2], truth)
        assert ok, (k, why)

    confirmed, in_water = 0, 0
    for k, t, r, state in _frames(world, path):
        pred = lying_prediction(INTR, Mount(), state, k)
        t_geo = geo.update(pred, state, t, r.rgb)
        t_liar = liar.update(pred, state, t)
        if t_geo.valid:
            confirmed += 1
            safe(k, t_geo)
        if t_liar.valid:
            in_water += "water" in check_target(world, *t_liar.position_ned_m[:2], truth)[1]
    return confirmed, in_water


def test_the_lying_model_gets_no_target_on_garden_pools():
    """A pass at 30 m over a lawn with three garden pools (7 × 3.6 m, the towns' size) that the liar calls flat
    ground: no confirmed disc touches water (the pools' floors lie a metre below the lawn), the lawn around
    them is confirmed, and the liar alone lands in them."""
    pools = [(20.0, 0.0, 3.5, 1.8), (14.0, -5.0, 3.5, 1.8), (26.0, 4.0, 3.5, 1.8)]
    path = [(-5.0 + 0.5 * k, 2.0 * math.sin(0.2 * k), -30.0) for k in range(80)]
    confirmed, in_water = _liar_over(_water_world(pools), path)
    assert confirmed > 20 and in_water > 0


def test_the_lying_model_gets_no_target_on_a_murky_pond():
    """An 18 m pond that shows no floor (the country's water), which the liar calls flat ground and lands in:
    no confirmed disc touches it. Its surface's only texture is the camera's noise, so it cannot confirm, not
    even where DIS fills its flow in from the bank (before the noise-relative texture check, cells a few metres
    inside read as level ground and discs reached over the water; image_checks)."""
    pond_n, pond_e, half_m = 20.0, 0.0, 9.0
    world = _water_world([(pond_n, pond_e, half_m, half_m)], sim.Style.RURAL)
    path = [(-5.0 + 0.5 * k, 2.0 * math.sin(0.2 * k), -30.0) for k in range(60)]
    confirmed, in_water = _liar_over(world, path)
    assert confirmed > 20 and in_water > 0                # not vacuous: targets confirmed, the liar lands in it
