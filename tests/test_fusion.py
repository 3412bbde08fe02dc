"""Fusion (ARCHITECTURE.md §6) on analytic scenes rendered by exact ray casting (tests/fusion_scenes.py)."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from edge_landing.runtime.core.camera import (
    Attitude,
    Intrinsics,
    Mount,
    ned_from_camera,
)
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.geometry import hvo_from_normals, normals_from_depth
from edge_landing.runtime.core.messages import Prediction
from edge_landing.runtime.fusion.fuser import (
    DEGRADED_NO_HVO,
    FusionConfig,
    LandingFuser,
)
from tests.fusion_scenes import (
    Box,
    Scene,
    check_target_on_gt,
    gt_disc_ok,
    prediction,
    state_at,
    target_ned,
    tilted_plane,
)

INTR = Intrinsics.from_hfov(160, 120)
MOUNT = Mount()                       # 45° below the horizon
ALT_M = 40.0
# Single frames / analytic renders without camera images: motion geometry cannot confirm, so these
# network-evidence tests run with the explicit flag (ARCHITECTURE.md §11).
CFG = FusionConfig(allow_unconfirmed=True)
NEED_M = CFG.required_clearance_m


def fuse(scene: Scene, position=(0.0, 0.0, -ALT_M), attitude=Attitude(), cfg=CFG, with_position=False, hvo=True):
    render = scene.render(INTR, MOUNT, attitude, position)
    fuser = LandingFuser(cfg, INTR, MOUNT)
    target = fuser.update(prediction(render, hvo=hvo), state_at(0.0, position, attitude, with_position))
    return target, fuser, render


def dist_to_box_m(p, box: Box) -> float:
    dn = max(box.lo[0] - p[0], 0.0, p[0] - box.hi[0])
    de = max(box.lo[1] - p[1], 0.0, p[1] - box.hi[1])
    return math.hypot(dn, de)


def test_flat_ground_gives_a_target_on_the_plane():
    target, fuser, render = fuse(Scene())
    assert target.valid, target.reason
    p = target_ned(target, (0, 0, -ALT_M))
    assert abs(p[2]) < 0.05                                   # on the ground (down = 0)
    assert target.clearance_m >= NEED_M
    assert target.range_m == pytest.approx(float(np.linalg.norm(target.position_body_frd_m)))
    assert 0.0 < target.confidence <= 1.0 and target.reason == ""
    assert target.position_ned_m is None                      # no vehicle position: no NED output
    assert "fusion" in target.timings_s
    ok, n, why = gt_disc_ok(render, p, NEED_M)
    assert ok and n > 0, why
    # The grid is exposed for overlays: the target's cell is landable and has the reported clearance.
    cell = fuser.grid.cell_of(p[0], p[1])
    assert fuser.grid.landable[cell] and fuser.grid.clearance_m[cell] == pytest.approx(target.clearance_m)
    assert fuser.grid.cell_centres_m().shape == fuser.grid.shape + (2,)


def test_angles_point_at_the_target_in_the_image():
    att = Attitude(0.05, -0.08, 0.7)
    pos = (3.0, -2.0, -35.0)
    target, _, _ = fuse(Scene(), pos, att, with_position=True)
    assert target.valid, target.reason
    # Recompute the camera-frame vector from the NED output and compare with the reported angles.
    cam = ned_from_camera(MOUNT, att).T @ (target.position_ned_m - np.asarray(pos))
    assert math.atan2(cam[0], cam[2]) == pytest.approx(target.angle_x_rad, abs=1e-9)
    assert math.atan2(cam[1], cam[2]) == pytest.approx(target.angle_y_rad, abs=1e-9)
    np.testing.assert_allclose(target_ned(target, pos, att), target.position_ned_m, atol=1e-9)
    u, v = INTR.project(cam)
    assert 0 <= u < INTR.width and 0 <= v < INTR.height       # the spot was seen in this frame
    assert 0 < target.size_y_rad <= target.size_x_rad


def test_box_obstacle_keeps_the_target_away():
    # A 4 m pillar right where the nearest clear ground would be (about 10 m ahead).
    box = Box((8.0, -2.0, -15.0), (12.0, 2.0, 0.0))
    target, _, render = fuse(Scene(boxes=(box,)))
    assert target.valid, target.reason
    p = target_ned(target, (0, 0, -ALT_M))
    assert dist_to_box_m(p, box) >= NEED_M
    ok, _, why = gt_disc_ok(render, p, NEED_M)
    assert ok, why


def test_steep_slope_everywhere_gives_no_target():
    target, _, _ = fuse(Scene(planes=(tilted_plane(math.radians(30.0), (60.0, 0.0, 0.0)),)))
    assert not target.valid
    assert target.reason.startswith("no safe spot")
    assert target.position_body_frd_m is None


def test_nan_depth_gives_no_target():
    render = Scene().render(INTR, MOUNT, Attitude(), (0, 0, -ALT_M))
    fuser = LandingFuser(CFG, INTR, MOUNT)
    pred = Prediction(3, 1.0, np.full_like(render.depth_m, np.nan), render.probs())
    target = fuser.update(pred)
    assert not target.valid and target.frame_id == 3 and "no usable depth" in target.reason


def test_absurdly_far_depth_is_dropped_without_overflow():
    """A patch of 1e30 m (a broken model) must not overflow the normals' float32 products into a fusion error."""
    render = Scene().render(INTR, MOUNT, Attitude(), (0, 0, -ALT_M))
    fuser = LandingFuser(CFG, INTR, MOUNT)
    depth = render.depth_m.copy()
    depth[20:40, 20:40] = 1e30
    with np.errstate(all="raise"):
        target = fuser.update(Prediction(0, 0.0, depth, render.probs()))
    assert target.valid, target.reason


def test_stale_frame_gives_no_target():
    render = Scene().render(INTR, MOUNT, Attitude(), (0, 0, -ALT_M))
    fuser = LandingFuser(CFG, INTR, MOUNT)
    assert fuser.update(prediction(render, t_s=10.0), now_s=10.2).valid
    late = fuser.update(prediction(render, t_s=10.0), now_s=10.0 + CFG.stale_after_s + 0.1)
    assert not late.valid and late.reason.startswith("stale frame")


def test_bad_predictions_give_reasons_not_exceptions():
    render = Scene().render(INTR, MOUNT, Attitude(), (0, 0, -ALT_M))
    fuser = LandingFuser(CFG, INTR, MOUNT)
    cases = {
        "invalid prediction: model fault": Prediction(0, 0.0, render.depth_m, render.probs(), valid=False,
                                                      reason="model fault"),
        "no depth": Prediction(0, 0.0, None, render.probs()),
        "HVO probabilities must be": Prediction(0, 0.0, render.depth_m, render.probs()[..., :2]),
        "depth must be": Prediction(0, 0.0, render.depth_m[0], None),
        "capture time": Prediction(0, float("nan"), render.depth_m, None),
    }
    for expected, pred in cases.items():
        target = fuser.update(pred)
        assert not target.valid and expected in target.reason, (expected, target.reason)
    bad_state = state_at(0.0, (0, 0, np.nan), Attitude())
    assert "invalid telemetry" in fuser.update(prediction(render), bad_state).reason


def test_depth_only_model_is_degraded_not_refused():
    with_hvo, _, _ = fuse(Scene())
    depth_only, _, render = fuse(Scene(), hvo=False)
    assert depth_only.valid and depth_only.reason == DEGRADED_NO_HVO
    assert depth_only.confidence < with_hvo.confidence
    ok, _, why = gt_disc_ok(render, target_ned(depth_only, (0, 0, -ALT_M)), NEED_M)
    assert ok, why


def test_pixel_noise_in_depth_is_tolerated():
    """Network depth is noisy at the pixel level: 1 % white noise must not hide flat ground."""
    render = Scene().render(INTR, MOUNT, Attitude(), (0, 0, -ALT_M))
    noise = np.random.default_rng(0).standard_normal(render.depth_m.shape).astype(np.float32)
    noisy = render.depth_m * (1.0 + 0.01 * noise)
    target = LandingFuser(CFG, INTR, MOUNT).update(Prediction(0, 0.0, noisy, render.probs()))
    assert target.valid, target.reason
    assert abs(target.position_body_frd_m[2] - ALT_M) < 0.5
    unsmoothed = LandingFuser(replace(CFG, depth_smoothing_px=1), INTR, MOUNT)
    assert not unsmoothed.update(Prediction(0, 0.0, noisy, render.probs())).valid   # why the smoothing exists


def test_all_vertical_hvo_gives_no_target():
    render = Scene().render(INTR, MOUNT, Attitude(), (0, 0, -ALT_M))
    probs = np.zeros(render.depth_m.shape + (3,), np.float32)
    probs[..., 1] = 1.0
    target = LandingFuser(CFG, INTR, MOUNT).update(Prediction(0, 0.0, render.depth_m, probs))
    assert not target.valid and target.reason.startswith("no safe spot")


def test_inputs_at_other_sizes_are_resized():
    big = Intrinsics.from_hfov(320, 240)
    render = Scene().render(big, MOUNT, Attitude(), (0, 0, -ALT_M))
    small_depth = render.depth_m[::4, ::4]                    # 60×80 depth, 240×320 HVO, intrinsics at 240×320
    fuser = LandingFuser(CFG, big, MOUNT)
    target = fuser.update(Prediction(0, 0.0, small_depth, render.probs()))
    assert target.valid, target.reason
    assert abs(target.position_body_frd_m[2] - ALT_M) < 0.3


def test_flat_votes_match_the_shared_hvo_labels():
    """Fusion's inline slope test is geometry.normals_from_points' recipe: same verdicts on the same pixels."""
    box = Box((15.0, -6.0, -8.0), (25.0, 6.0, 0.0))
    render = Scene(boxes=(box,), planes=(tilted_plane(0.1), )).render(INTR, MOUNT, Attitude(), (0, 0, -ALT_M))
    up_cam = ned_from_camera(MOUNT).T @ np.array([0.0, 0.0, -1.0])
    labels = hvo_from_normals(normals_from_depth(render.depth_m, INTR), up_cam)
    fuser = LandingFuser(replace(CFG, working_hw=(INTR.height, INTR.width), depth_smoothing_px=1), INTR, MOUNT)
    captured = {}
    original = fuser._grid.add_cells

    def spy(samples):
        captured["flat"] = samples[4].copy()          # rows: row, column, height, horizontal, flat
        return original(samples)

    fuser._grid.add_cells = spy
    fuser.update(prediction(render, hvo=False))
    # Depth-derived flat share of all samples equals the share of samples from H-labelled pixels.
    inner = labels[1:-1, 1:-1]
    share_geometry = np.mean(inner[inner != 255] == 0)
    assert captured["flat"].size > 1000
    # (samples weight pixels by their footprint, so the shares agree closely rather than exactly)
    assert abs(float(np.mean(captured["flat"])) - share_geometry) < 0.03


def test_hysteresis_keeps_the_target_when_a_slightly_better_spot_appears():
    render = Scene().render(INTR, MOUNT, Attitude(), (0, 0, -ALT_M))
    # Frame 1: the net calls everything nearer than 20 m "other", so the target lies beyond it.
    probs_far = render.probs()
    near = render.points_ned[..., 0] < 20.0
    probs_far[near] = (0.0, 0.0, 1.0)
    results = {}
    for hysteresis in (CFG.hysteresis_m, 0.0):
        fuser = LandingFuser(replace(CFG, hysteresis_m=hysteresis), INTR, MOUNT)
        first = fuser.update(Prediction(0, 0.0, render.depth_m, probs_far))
        # Frame 2: the near ground is horizontal too; a nearer spot scores better by travel_penalty × ~10 m.
        second = fuser.update(Prediction(1, 0.1, render.depth_m, render.probs()))
        results[hysteresis] = (first, second)
    first, second = results[CFG.hysteresis_m]
    assert first.valid and second.valid
    assert first.position_body_frd_m[0] >= 20.0
    np.testing.assert_allclose(second.position_body_frd_m, first.position_body_frd_m, atol=1e-6)
    # Without hysteresis the same frames do switch, so the test above is not vacuous.
    first0, second0 = results[0.0]
    assert second0.position_body_frd_m[0] < first0.position_body_frd_m[0] - 5.0


def test_ned_grid_keeps_the_target_fixed_while_the_vehicle_moves():
    boxes = (Box((8.0, -3.0, -10.0), (12.0, 3.0, 0.0)), Box((20.0, 4.0, -6.0), (26.0, 12.0, 0.0)))
    scene = Scene(boxes=boxes)
    fuser = LandingFuser(CFG, INTR, MOUNT)
    targets = []
    for i in range(8):
        t_s = 0.1 * i
        pos = np.array([2.0 * t_s, 0.5 * t_s, -ALT_M + 0.3 * t_s])
        att = Attitude(0.03 * math.sin(i), -0.05 + 0.02 * math.cos(i), 0.2 + 0.05 * i)
        render = scene.render(INTR, MOUNT, att, pos)
        target = fuser.update(prediction(render, i, t_s), state_at(t_s, pos, att), now_s=t_s + 0.05)
        assert target.valid, (i, target.reason)
        np.testing.assert_allclose(target_ned(target, pos, att), target.position_ned_m, atol=1e-9)
        targets.append(target)
    first = targets[0].position_ned_m
    for t in targets[1:]:
        np.testing.assert_allclose(t.position_ned_m[:2], first[:2], atol=1e-9)
        assert abs(t.position_ned_m[2] - first[2]) < 0.05
    assert fuser.grid.frame == "ned"
    # The body-frame vector changes as the vehicle moves: the target is fixed in the world, not in the body.
    assert np.linalg.norm(targets[-1].position_body_frd_m - targets[0].position_body_frd_m) > 1.0


def test_ned_evidence_decays():
    render = Scene().render(INTR, MOUNT, Attitude(), (0, 0, -ALT_M))
    fuser = LandingFuser(CFG, INTR, MOUNT)
    fuser.update(prediction(render, 0, 0.0), state_at(0.0, (0, 0, -ALT_M)))
    c0 = float(fuser.grid.count.sum())
    fuser.update(prediction(render, 1, CFG.decay_s), state_at(CFG.decay_s, (0, 0, -ALT_M)))
    c1 = float(fuser.grid.count.sum())
    assert c1 == pytest.approx(c0 * (1.0 + math.exp(-1.0)), rel=0.02)


def test_config_is_checked_where_it_enters():
    with pytest.raises(InputError, match="cell_m"):
        FusionConfig(cell_m=0.0)
    with pytest.raises(InputError, match="grid_radius_m"):
        FusionConfig(grid_radius_m=3.0)
    with pytest.raises(InputError, match="cells across"):
        FusionConfig(grid_radius_m=2000.0, cell_m=0.25)       # 16000 cells across


# --- Ground truth: every target is on GT-horizontal ground with the promised clearance -------------------
# (the same check against the synthetic generator's ground truth is in test_fusion_sim.py)

@pytest.mark.parametrize("seed", [0, 1, 2])
def test_analytic_town_targets_lie_on_safe_ground(seed):
    rng = np.random.default_rng(seed)
    centres = rng.uniform([0, -40, 0], [70, 40, 0], size=(25, 3))
    sizes = rng.uniform([3, 3, 2], [14, 14, 20], size=(25, 3))
    boxes = tuple(Box(tuple(c - s * [0.5, 0.5, 0] - [0, 0, s[2]]), tuple(c + s * [0.5, 0.5, 0]))
                  for c, s in zip(centres, sizes))
    scene = Scene(boxes=boxes)
    valid = 0
    for k in range(4):
        pos = (rng.uniform(-10, 10), rng.uniform(-10, 10), -rng.uniform(30, 70))
        att = Attitude(rng.normal(0, 0.03), rng.normal(0, 0.03), rng.uniform(-0.5, 0.5))
        target, _, render = fuse(scene, pos, att, with_position=True)
        if target.valid:
            valid += 1
            check_target_on_gt(target, render, f"seed {seed} view {k}")
    assert valid >= 2


def test_views_without_safe_area_give_no_target():
    # A steep wall 8 m ahead: only a strip of ground narrower than the clear disc is visible.
    wall = Box((8.0, -200.0, -300.0), (20.0, 200.0, 0.0))
    target, _, _ = fuse(Scene(boxes=(wall,)))
    assert not target.valid and target.reason.startswith("no safe spot"), target.reason
    # A dense block: 3 m pillars of many heights on a 4.5 m pitch (1.5 m streets, roofs too small to land on),
    # filling everything the grid covers (a 30 m grid keeps the block, and so the render, small).
    rng = np.random.default_rng(0)
    pillars = tuple(Box((n, e, -float(rng.uniform(6, 30))), (n + 3.0, e + 3.0, 0.0))
                    for n in np.arange(-36.0, 36.0, 4.5) for e in np.arange(-36.0, 36.0, 4.5))
    target, _, _ = fuse(Scene(boxes=pillars), cfg=replace(CFG, grid_radius_m=30.0))
    assert not target.valid and target.reason.startswith("no safe spot"), target.reason


def test_clearance_is_a_safe_lower_bound_to_the_nearest_bad_cell():
    from edge_landing.runtime.fusion.grid import clearance_from_mask

    cell = 0.5
    mask = np.ones((41, 41), bool)
    mask[20, 20] = False                       # one obstacle cell; the mask border is landable here
    clear = clearance_from_mask(mask, cell)
    assert clear[20, 20] == 0.0
    # 10 cells east: centre-to-centre 5 m, minus half a cell diagonal (the obstacle's nearest corner region);
    # the unknown ground past the mask's edge is 11 cells away.
    assert clear[20, 30] == pytest.approx(10 * cell - cell / math.sqrt(2), abs=1e-4)
    # Every cell centre is at least its clearance away from every point of the obstacle cell.
    rows, cols = np.mgrid[0:41, 0:41]
    nearest = np.hypot(np.maximum(np.abs(rows - 20) - 0.5, 0), np.maximum(np.abs(cols - 20) - 0.5, 0)) * cell
    assert np.all(clear <= nearest + 1e-5)


def test_clearance_is_the_exact_distance_the_same_on_every_call():
    """OpenCV's exact distance transform carries float error that changed between identical calls (a replay's
    clearances differed in the last bit); the grid's clearance is the exact Euclidean distance, every time."""
    from edge_landing.runtime.fusion.grid import clearance_from_mask

    cell = 0.5
    rng = np.random.default_rng(7)
    mask = rng.random((60, 90)) > 0.02                    # scattered obstacle cells, large open stretches
    mask[0, :] = mask[-1, :] = False
    ring = np.pad(mask, 1, constant_values=False)         # past the mask's edge: unknown, not landable
    bad = np.argwhere(~ring) - 1
    rows, cols = np.nonzero(mask)
    d2 = ((rows[:, None] - bad[None, :, 0]) ** 2 + (cols[:, None] - bad[None, :, 1]) ** 2).min(axis=1)
    exact = np.zeros(mask.shape, np.float32)
    exact[rows, cols] = np.maximum(np.sqrt(d2.astype(np.float32)) * np.float32(cell)
                                   - np.float32(cell / math.sqrt(2.0)), np.float32(0.0))
    first = clearance_from_mask(mask, cell)
    assert np.array_equal(first, exact)
    for _ in range(20):
        # Fresh copies at other addresses: nothing about the call may change the answer.
        assert np.array_equal(clearance_from_mask(np.array(mask, copy=True), cell), first)


def test_a_cell_at_the_edge_of_the_mask_is_not_clear_of_what_lies_past_it():
    """Unknown ground past the grid's edge counts as an obstacle: a confirmed view whose landable cells reached
    the grid's edge once sent a spot 1.8 m from a car just outside the grid (urban 1505, docs/MEASUREMENTS.md)."""
    from edge_landing.runtime.fusion.grid import clearance_from_mask

    cell = 0.5
    mask = np.zeros((30, 30), bool)
    mask[5:25, 0:20] = True                               # open ground up to the west edge
    clear = clearance_from_mask(mask, cell)
    west = np.arange(20)
    # Column c is c + 1 cells from the column past the edge (-1): never farther from the unknown than that.
    assert np.all(clear[15, west] <= (west + 1) * cell - cell / math.sqrt(2) + 1e-5)
    assert clear[15, 0] == pytest.approx(cell - cell / math.sqrt(2), abs=1e-5)
    assert clear[15, 0] < 2.0 and clear[15, 10] > 2.0   # a 2 m disc fits only away from the edge
    full = clearance_from_mask(np.ones((9, 9), bool), cell)   # all landable: bounded by the edge alone
    assert full[4, 4] == pytest.approx(5 * cell - cell / math.sqrt(2), abs=1e-5)
    assert full.max() == full[4, 4]


def test_footprint_splatting_leaves_no_holes_in_flat_ground():
    for yaw in (0.0, 0.4, math.pi / 4):
        _, fuser, _ = fuse(Scene(), attitude=Attitude(0.0, 0.0, yaw))
        observed = fuser.grid.count > 0
        inner = observed[1:-1, 1:-1]
        enclosed = observed[:-2, 1:-1] & observed[2:, 1:-1] & observed[1:-1, :-2] & observed[1:-1, 2:]
        assert not np.any(~inner & enclosed), yaw


def test_spot_choice_is_the_best_scoring_cell_first_in_grid_order():
    """The spot is the candidate cell with the best score (clearance up to saturation, less the travel penalty),
    the first in grid order on ties, wherever it lies relative to the vehicle."""
    from edge_landing.runtime.fusion import landing
    from edge_landing.runtime.fusion.grid import GridView

    rng = np.random.default_rng(5)
    cfg = FusionConfig()
    n = 120
    for trial in range(30):
        clearance = np.round(rng.uniform(0.0, 6.0, (n, n)), 1).astype(np.float32)   # ties on purpose
        clearance[rng.random((n, n)) < rng.uniform(0.0, 0.9)] = 0.0
        sums = np.ones((5, n, n), np.float32)
        view = GridView("ned", 0.5, -30.0, -30.0, 0.0, sums, clearance > 0, clearance)
        here = (float(rng.uniform(-40, 40)), float(rng.uniform(-40, 40)))
        pick = landing.choose_spot(view, here, cfg)
        rows, cols = np.nonzero(clearance >= cfg.required_clearance_m - 1e-6)
        north, east = -30.0 + (rows + 0.5) * 0.5, -30.0 + (cols + 0.5) * 0.5
        scores = landing._score(clearance[rows, cols], np.hypot(north - here[0], east - here[1]), cfg)
        best = int(np.argmax(scores))
        assert pick is not None, trial
        assert (pick.north_m, pick.east_m) == (float(north[best]), float(east[best])), trial
