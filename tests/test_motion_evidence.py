"""Motion-geometry evidence rules (ARCHITECTURE.md §11): where heights land in NED, what revokes a confirmation,
what makes an obstacle. Renders are real sim worlds (Embree ray casting); the grid is fed real ParallaxResult
arrays written out so that each rule is tested on its own."""
from __future__ import annotations

import math

import numpy as np
import pytest

from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
from edge_landing.runtime.fusion.motion import CameraPose, MotionConfig, MotionStage, ParallaxResult
from edge_landing.runtime.fusion.motion_grid import GeometryGrid

sim = pytest.importorskip("edge_landing.sim", reason="the sim extra (embreex) renders the test worlds")
from tests.test_motion import EFFECTS, _flat_world  # noqa: E402

INTR = Intrinsics.from_hfov(320, 240)
MOUNT = Mount()


def test_ground_below_a_roof_reading_is_placed_and_weighed_at_its_own_range():
    """The rangefinder reads a roof 15 m under the vehicle while the field the camera sees is 40 m below: the
    ground's pixels go to their NED point on the field (not on the roof's plane), and their uncertainty is
    that of the field's range, larger than the plane's."""
    world = _flat_world([[40.0, 0.0, 3.0, 3.0, 2.0]])
    renderer = sim.Renderer(world, INTR, MOUNT)
    stage = MotionStage(MotionConfig(), INTR, MOUNT)
    rng = np.random.default_rng(1)
    result = None
    for k, east in enumerate((-2.0, 2.0)):
        p = np.array([0.0, east, -40.0])
        r = renderer.render(p, Attitude(), EFFECTS, rng)
        pose = CameraPose.of(MOUNT, Attitude(), p, 15.0)                  # the roof's reading, not 40 m
        result = stage.update(r.rgb, pose, 0.1 * k, focus_ned_m=np.array([40.0, 0.0, 0.0]))
    assert result is not None, stage.last_reason
    seen = np.isfinite(result.height_m)
    assert seen.mean() > 0.5
    down = result.ned_m[2][seen]
    assert abs(float(np.median(down))) < 1.0, np.median(down)          # on the field (down 0), not at -25
    # On the plane 15 m below, σ would be d·σn/|g|; the field 40 m below is measured (40/15)² times worse.
    assert float(np.median(result.sigma_m[seen])) > 0.05


def _result(height: np.ndarray, det: np.ndarray, unexplained: np.ndarray, t: float, sigma: float = 0.1
            ) -> ParallaxResult:
    """A frame's evidence on a 20×20-pixel window whose pixels fall 4 per 0.5 m cell around (5, 5) m NED."""
    h, w = height.shape
    rr, cc = np.mgrid[0:h, 0:w].astype(np.float32)
    ned = np.stack([5.0 + rr * 0.25, 5.0 + cc * 0.25, np.zeros_like(rr)])
    return ParallaxResult(t, slice(0, h), slice(0, w), height.astype(np.float32),
                          np.full((h, w), sigma, np.float32), det.astype(np.float32), ned.astype(np.float32),
                          10.0, 1.0, np.zeros(6), 0.2, unexplained)


def _grid() -> GeometryGrid:
    return GeometryGrid(0.5, 20.0, 30.0, 0.5)


def _cell(grid: GeometryGrid, north: float, east: float) -> tuple[int, int]:
    return int((north - grid.north0_m) / grid.cell_m), int((east - grid.east0_m) / grid.cell_m)


def test_no_evidence_does_not_revoke_but_unexplained_pixels_do():
    grid = _grid()
    shape = (20, 20)
    zeros, none = np.zeros(shape), np.zeros(shape, bool)
    grid.add(_result(zeros, np.full(shape, 0.3), none, 0.0))
    cell = _cell(grid, 7.6, 7.6)
    assert grid.view(grid.north0_m, grid.east0_m, (grid.size, grid.size), 0.0).clear[cell]
    # Out of the reference frame (no height, not unexplained) and unresolved (height, detectable inf): no evidence.
    grid.add(_result(np.full(shape, np.nan), np.full(shape, np.nan), none, 0.2))
    grid.add(_result(zeros, np.full(shape, np.inf), none, 0.4))
    assert grid.view(grid.north0_m, grid.east0_m, (grid.size, grid.size), 0.4).clear[cell]
    # The flow could not explain most of it (occlusion by something tall): the confirmation is revoked.
    grid.add(_result(np.full(shape, np.nan), np.full(shape, np.inf), ~none, 0.6))
    assert not grid.view(grid.north0_m, grid.east0_m, (grid.size, grid.size), 0.6).clear[cell]


def test_an_outlier_pixel_is_not_an_obstacle_a_standing_thing_is_and_grows_after_the_vote():
    grid = _grid()
    shape = (20, 20)
    none = np.zeros(shape, bool)
    det = np.full(shape, 0.3)
    for k in range(10):
        height = np.zeros(shape)
        height[(3 * k) % 20, (7 * k) % 20] = 2.0           # one heavy-tail pixel a frame, somewhere else each time
        height[10:12, 10:12] = 1.0                          # a 0.5 m wide, 1 m tall box (one cell, all its pixels)
        grid.add(_result(height, det, none, 0.2 * k))
    view = grid.view(grid.north0_m, grid.east0_m, (grid.size, grid.size), 1.8)
    box = _cell(grid, 7.6, 7.6)
    assert view.obstacle[box]
    assert view.obstacle[box[0] + 2, box[1]] and not view.clear[box[0] + 2, box[1]]   # grown by 1 m
    far = _cell(grid, 5.1, 9.6)
    assert not view.obstacle[far] and view.clear[far]
    assert view.obstacle.sum() <= 25                    # the box grown by 1 m, not the outliers' cells


def test_the_stage_runs_every_geometry_interval():
    world = _flat_world([[80.0, 60.0, 1.0, 1.0, 1.0]])
    renderer = sim.Renderer(world, INTR, MOUNT)
    fuser = LandingFuser(FusionConfig(), INTR, MOUNT)
    from edge_landing.benchmarks.lying_model import lying_prediction
    from edge_landing.runtime.core.messages import VehicleState

    rng = np.random.default_rng(2)
    ran = []
    for k in range(8):
        p = np.array([0.0, -4.0 + 1.0 * k, -30.0])
        state = VehicleState(0.1 * k, Attitude(), p, 30.0, "sim")
        r = renderer.render(p, Attitude(), EFFECTS, rng)
        target = fuser.update(lying_prediction(INTR, MOUNT, state, k), state, 0.1 * k, r.rgb)
        ran.append("runs every" not in (target.reason + target.evidence))
    assert ran == [True, False] * 4
    assert math.isclose(FusionConfig().geometry_interval_s, 0.2)
