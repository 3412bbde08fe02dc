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


def _grid(**kwargs) -> GeometryGrid:
    return GeometryGrid(0.5, 20.0, 30.0, 0.5, **kwargs)


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


def test_a_pair_too_coarse_for_a_thin_wall_does_not_confirm_what_a_finer_one_does():
    """Detecting 0.3 m where the flow's patch is three times wider than a thin wall (thin factor 3): a wall
    there would read at a third of its height, so the pair needs 0.3 × 3 = 0.9 m <= 0.5 m to confirm; it
    does not, nor do ten such pairs fused. Where the patch is narrower (factor 1) the same pair confirms."""
    from dataclasses import replace

    shape = (20, 20)
    zeros, none = np.zeros(shape), np.zeros(shape, bool)
    coarse, fine = _grid(), _grid()
    for k in range(10):
        r = _result(zeros, np.full(shape, 0.3), none, 0.2 * k)
        coarse.add(replace(r, thin_factor=np.full(shape, 3.0, np.float32)))
        fine.add(replace(r, thin_factor=np.ones(shape, np.float32)))
    cell = _cell(coarse, 7.6, 7.6)
    for grid, clear in ((coarse, False), (fine, True)):
        view = grid.view(grid.north0_m, grid.east0_m, (grid.size, grid.size), 1.8)
        assert view.clear[cell] == clear and not view.obstacle[cell]
        assert view.detectable_m[cell] <= 0.3          # what it could detect of a wide obstacle is the same


@pytest.mark.parametrize("value", [-0.1, math.nan])
def test_thin_obstacle_width_is_checked(value):
    from edge_landing.runtime.core.errors import InputError

    with pytest.raises(InputError, match="thin_obstacle_m"):
        MotionConfig(thin_obstacle_m=value)
    assert MotionConfig(thin_obstacle_m=0.0).thin_obstacle_m == 0.0          # 0: off


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


def test_the_view_follows_evidence_through_moves_and_window_offsets():
    """The view computes only where evidence was ever added: moved with the grid, cut where it leaves the grid,
    and read through a window offset from the grid's own cells, it says the same as before the move."""
    grid = _grid()
    shape = (20, 20)
    height = np.zeros(shape)
    height[10:12, 10:12] = 1.0                              # an obstacle cell amid clear ones, at (7.5-8, 7.5-8) m
    for k in range(5):
        grid.add(_result(height, np.full(shape, 0.3), np.zeros(shape, bool), 0.2 * k))
    origin0 = (grid.north0_m, grid.east0_m)
    before = grid.view(*origin0, (grid.size, grid.size), 0.8)
    assert before.clear.sum() > 0 and before.obstacle.sum() > 0

    def cell(north: float, east: float, origin: tuple[float, float]) -> tuple[int, int]:
        return int(math.floor((north - origin[0]) / 0.5)), int(math.floor((east - origin[1]) / 0.5))

    points = [(5.1 + 0.5 * i, 5.1 + 0.5 * j) for i in range(10) for j in range(10)]   # over the evidence
    # Moved (whole cells) with the evidence still inside; read through the grid's own window and an offset one.
    grid.centre_on(12.0, -3.0)
    for origin, size in (((grid.north0_m, grid.east0_m), grid.size), ((grid.north0_m + 3.0, grid.east0_m + 20.0), 50)):
        after = grid.view(*origin, (size, size), 0.8)
        for north, east in points:
            new, old = cell(north, east, origin), cell(north, east, origin0)
            assert after.clear[new] == before.clear[old] and after.obstacle[new] == before.obstacle[old]
            assert after.detectable_m[new] == before.detectable_m[old]
    # Moved so that the grid's edge cuts through the evidence: what left is gone, what stayed is unchanged.
    grid.centre_on(26.0, 0.0)
    assert 5.0 < grid.north0_m < 10.0
    origin = (grid.north0_m, grid.east0_m)
    cut = grid.view(*origin, (grid.size, grid.size), 0.8)
    for north, east in points:
        if north >= grid.north0_m:
            new, old = cell(north, east, origin), cell(north, east, origin0)
            assert cut.clear[new] == before.clear[old] and cut.obstacle[new] == before.obstacle[old]
    window = grid.view(origin[0] - 5.0, origin[1], (grid.size, grid.size), 0.8)   # 10 rows before the grid
    assert not window.clear[:10].any() and np.isinf(window.detectable_m[:10]).all()
    grid.centre_on(500.0, 500.0)                             # everything left the grid: nothing is kept
    gone = grid.view(grid.north0_m, grid.east0_m, (grid.size, grid.size), 0.8)
    assert not gone.clear.any() and not gone.obstacle.any() and np.isinf(gone.detectable_m).all()


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
        assert fuser.geometry_ran == ran[-1]
    assert ran == [True, False] * 4
    assert math.isclose(FusionConfig().geometry_interval_s, 0.2)
    # A frame that stops before geometry (an invalid prediction, due for a run by time) ran nothing, even
    # right after a frame that did.
    from edge_landing.runtime.core.messages import Prediction

    state = VehicleState(0.8, Attitude(), np.array([0.0, 4.0, -30.0]), 30.0, "sim")
    fuser.update(lying_prediction(INTR, MOUNT, state, 8), state, 0.8, r.rgb)
    assert fuser.geometry_ran
    fuser.update(Prediction(9, 1.0, None, None, False, "decode failed"), state, 1.0, r.rgb)
    assert not fuser.geometry_ran


def test_fused_pairs_confirm_what_no_single_pair_could_and_show_what_none_saw():
    """Noisy pairs (each detecting 0.72 m) together detect 0.48 m (the gain capped at 1.5): flat ground gets
    confirmed after a few frames, and a 0.5 m step that no single pair could see stands out as an obstacle."""
    shape = (20, 20)
    none = np.zeros(shape, bool)
    rng = np.random.default_rng(3)
    flat, step = _grid(), _grid()
    for k in range(6):
        noise = rng.normal(0.0, 0.05, shape)
        flat.add(_result(noise, np.full(shape, 0.72), none, 0.2 * k, sigma=0.72 / 3))
        step.add(_result(0.5 + noise, np.full(shape, 0.72), none, 0.2 * k, sigma=0.72 / 3))
        if k == 0:    # one pair alone: measured to 0.72 m, neither confirmed nor an obstacle
            view = flat.view(flat.north0_m, flat.east0_m, (flat.size, flat.size), 0.0)
            assert not view.clear[_cell(flat, 7.6, 7.6)]
    cell = _cell(flat, 7.6, 7.6)
    view = flat.view(flat.north0_m, flat.east0_m, (flat.size, flat.size), 1.0)
    assert view.clear[cell] and not view.obstacle[cell]
    assert float(view.detectable_m[cell]) == pytest.approx(0.48, abs=1e-3)    # capped: 0.72 / 1.5, not 0.72 / √6
    view = step.view(step.north0_m, step.east0_m, (step.size, step.size), 1.0)
    assert view.obstacle[cell] and not view.clear[cell]


def test_pairs_that_agree_on_a_filled_surface_do_not_confirm_it_however_many():
    """A parked car's smooth paint: DIS fills its flow in from the ground around it the same way in every pair,
    so each pair reads it level (heights -0.3 to +0.4 m) while detecting no better than 0.9 m there. The errors
    are not independent; however many pairs agree, fusion credits at most 1.5x the best pair (0.6 m here,
    more than the 0.5 m obstacle height), so the cell is never confirmed. At 2x (0.45 m) it was: suburban 9783
    sent a target whose disc held a car's bonnet (docs/MEASUREMENTS.md, Water)."""
    shape = (20, 20)
    none = np.zeros(shape, bool)
    rng = np.random.default_rng(4)
    grid = _grid()
    lenient = _grid(max_fusion_gain=2.0)     # not vacuous: with the 2x credit of before, the same pairs confirm it
    cell = _cell(grid, 7.6, 7.6)
    for k in range(40):
        filled = rng.uniform(-0.3, 0.4) + rng.normal(0.0, 0.02, shape)      # one systematic reading per pair
        for g in (grid, lenient):
            g.add(_result(filled, np.full(shape, 0.9), none, 0.2 * k, sigma=0.9 / 3))
        view = grid.view(grid.north0_m, grid.east0_m, (grid.size, grid.size), 0.2 * k)
        assert not view.clear[cell], k
    assert float(view.detectable_m[cell]) == pytest.approx(0.6, abs=1e-3)
    assert lenient.view(lenient.north0_m, lenient.east0_m, (lenient.size, lenient.size), 8.0).clear[cell]


def test_a_hover_does_not_renew_what_moving_pairs_confirmed_a_noisy_moving_pair_does():
    """Pairs with baseline confirm a cell (fused credit); then the vehicle hovers: its pairs detect only 10 m
    there. They may not renew the confirmation, which ends ``memory_s`` after the last pair that could see an
    obstacle. Before, every such frame renewed it through the credit of the pairs seconds before (a 400-frame flight
    over suburban 6262: docs/MEASUREMENTS.md, "A confirmation renewed by pairs that could not see"). Moving pairs
    in heavy rain, each detecting 1.2 m (it could see a car), still renew it."""
    shape = (20, 20)
    none = np.zeros(shape, bool)
    rng = np.random.default_rng(6)
    hover, rain = GeometryGrid(0.5, 20.0, 5.0, 0.5), GeometryGrid(0.5, 20.0, 5.0, 0.5)
    cell = _cell(hover, 7.6, 7.6)
    for k in range(6):
        height = rng.normal(0.0, 0.05, shape)
        for g in (hover, rain):
            g.add(_result(height, np.full(shape, 0.72), none, 0.2 * k, sigma=0.24))
    assert hover.view(hover.north0_m, hover.east0_m, (hover.size, hover.size), 1.0).clear[cell]
    for k in range(6, 40):
        hover.add(_result(rng.normal(0.0, 1.0, shape), np.full(shape, 10.0), none, 0.2 * k, sigma=10.0 / 3))
        rain.add(_result(rng.normal(0.0, 0.1, shape), np.full(shape, 1.2), none, 0.2 * k, sigma=0.4))
    assert hover.view(hover.north0_m, hover.east0_m, (hover.size, hover.size), 5.8).clear[cell]     # within memory
    assert not hover.view(hover.north0_m, hover.east0_m, (hover.size, hover.size), 7.8).clear[cell]  # beyond it
    assert rain.view(rain.north0_m, rain.east0_m, (rain.size, rain.size), 7.8).clear[cell]


def test_ground_seen_under_an_overhang_is_not_seen_from_above():
    """A crown 3-7 m above the ground 2 m around a point: the camera sees the ground under its near edge, but
    the rays that would pass over that point end on the crown, so the point cannot confirm; open ground whose
    column stays in the window can, the top rows (their column leaves the window) cannot."""
    from edge_landing.runtime.fusion.parallax import column_seen, ned_points

    n_px = 96
    k = np.array([[n_px, 0.0, (n_px - 1) / 2], [0.0, n_px, (n_px - 1) / 2], [0.0, 0.0, 1.0]])
    pose = CameraPose.of(Mount(pitch_rad=-math.pi / 4), Attitude(), np.array([0.0, 0.0, -20.0]), 20.0)
    yy, xx = np.mgrid[0:n_px, 0:n_px].astype(np.float64)
    xc = np.stack([(xx - k[0, 2]) / n_px, (yy - k[1, 2]) / n_px])
    ground, _ = ned_points(pose, xc.reshape(2, -1), np.ones(n_px * n_px))
    ground = ground.reshape(3, n_px, n_px)
    measured = np.ones((n_px, n_px), bool)
    open_seen = column_seen(pose, k, (0, 0), xc, ground, measured, 8.0)
    # Bottom middle: the column (tilted towards the nadir's vanishing point) stays in the window.
    assert open_seen[-1, 24:72].all() and not open_seen[0].any()
    target = ground[:, 70, 48]                           # a ground point low in the image
    # The crown: 3-7 m up within 2 m of the target, in 0.5 m layers; a ray ends in the highest layer it meets
    # (rays descend away from the camera).
    ned = ground.copy()
    rays = ground - pose.position_ned_m[:, None, None]
    for up_m in np.arange(3.0, 7.01, 0.5):
        lam = (target[2] - up_m - pose.position_ned_m[2]) / rays[2]
        hit = pose.position_ned_m[:, None, None] + lam * rays
        under = (lam < 1.0) & (np.hypot(hit[0] - target[0], hit[1] - target[1]) <= 2.0)
        ned = np.where(under[None], hit, ned)
    seen = column_seen(pose, k, (0, 0), xc, ned, measured, 8.0)
    # The ground under the crown that the camera sees from the side (its own ray misses the crown).
    below = np.all(ned == ground, axis=0) & (np.hypot(ground[0] - target[0], ground[1] - target[1]) <= 1.9)
    assert below.sum() >= 10 and open_seen[below].all() and not seen[below].any()
    assert seen[88, 24] and seen[-1, 48]                 # beside the crown, and in front of it


def test_cell_recall_tells_obstacles_at_a_step_from_the_middle_of_a_wide_roof():
    """The benchmark's per-cell recall counts every cell standing 1 m above the terrain as an obstacle; the middle of
    a wide flat roof has no step anywhere near it (geometry measures heights above the local ground, and the safety
    judge accepts it too), so obstacles at a step are also counted on their own."""
    from types import SimpleNamespace

    from edge_landing.benchmarks.lying_model import cell_recall
    from edge_landing.runtime.fusion.motion_grid import GeometryView

    world = _flat_world([[0.0, 0.0, 10.0, 10.0, 3.0], [15.0, -15.0, 1.0, 1.0, 1.5]])   # a 20 m roof, a 2 m car
    size, cell = 80, 0.5
    grid = SimpleNamespace(north0_m=-20.0, east0_m=-20.0, cell_m=cell)
    centres = -20.0 + (np.arange(size) + 0.5) * cell
    north, east = np.meshgrid(centres, centres, indexing="ij")

    def counts(measured: np.ndarray) -> tuple[int, ...]:
        det = np.where(measured, np.float32(0.3), np.float32(np.inf))
        full = np.ones((size, size), bool)
        nan = np.full((size, size), np.nan, np.float32)
        geo = GeometryView(0.0, 0.5, full, full, det, nan, np.zeros((size, size)), nan)
        out = cell_recall(world, SimpleNamespace(geometry=geo, grid=grid), 40.0)
        assert out is not None
        return out

    assert counts(np.zeros((size, size), bool)) == (0,) * 8             # nothing measured: every count, as zeros
    car = (np.abs(north - 15.0) < 1.0) & (np.abs(east + 15.0) < 1.0)
    tall, hit, *_, step, step_hit = counts(car)
    assert tall == hit == step == step_hit == int(car.sum()) == 16     # every car cell stands at a step
    middle = (np.abs(north) < 7.0) & (np.abs(east) < 7.0)
    tall, hit, *_, step, step_hit = counts(middle)
    assert tall == hit == int(middle.sum()) and step == step_hit == 0  # no step within 1.5 m of the roof's middle
    rim = (np.abs(north) < 10.0) & (np.abs(east) < 10.0) & ~((np.abs(north) < 8.0) & (np.abs(east) < 8.0))
    tall, _, *_, step, _ = counts(rim)
    assert tall == int(rim.sum()) and 0.5 * tall < step < tall          # the rim's outer cells see the drop
