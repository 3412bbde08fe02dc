"""The plane a motion window is measured against, found from the images (fusion/plane_sweep.py, ARCHITECTURE.md §11).

A window on a roof 15 m above the ground leaves the roof with tens of pixels of parallax against the ground's
plane, more than the flow follows: without the sweep the pair fails and the roof is never measured. Worlds
are ray-cast renders (tests/test_motion.py's flat field with boxes), so the truth is known.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from edge_landing.runtime.core.camera import Attitude, Intrinsics
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.fusion.motion import CameraPose, MotionConfig, MotionStage
from edge_landing.runtime.fusion.plane_sweep import SweepConfig, sweep_plane

pytest.importorskip("edge_landing.sim", reason="the sim extra (embreex) renders the test worlds")
from edge_landing import sim  # noqa: E402
from tests.test_motion import EFFECTS, MOUNT, _flat_world  # noqa: E402

# The sim flights' camera: at 640×480 the 120×160 window is a quarter of the frame, so a roof fills it.
INTR = Intrinsics.from_hfov(640, 480)
ON = SweepConfig(enabled=True)          # opt-in (docs/MEASUREMENTS.md, "Roofs"): off in MotionConfig's default
ROOF_N, ROOF_H, POST_H = 40.0, 15.0, 1.5


def _pair(world, focus: np.ndarray, sweep: SweepConfig = ON):
    """Two frames from 60 m, 20 m apart sideways, the window on ``focus``: (result, last render, stage)."""
    stage = MotionStage(replace(MotionConfig(), sweep=sweep), INTR, MOUNT)
    renderer = sim.Renderer(world, INTR, MOUNT)
    rng = np.random.default_rng(1)
    result, render = None, None
    for k, east in enumerate((-10.0, 10.0)):
        position = np.array([0.0, east, -60.0])
        render = renderer.render(position, Attitude(), EFFECTS, rng)
        result = stage.update(render.rgb, CameraPose.of(MOUNT, Attitude(), position, 60.0), k * 0.5, focus)
    assert result is not None
    return result, render, stage


def _blocks(rows: list):
    """Town blocks on grass: facades and flat roofs (north, east, half_n, half_e, height_m), as sim/towns.py
    builds them."""
    from edge_landing.sim.world import Material

    return _flat_world(rows, side=Material.FACADE, tint=(0.55, 0.5, 0.45), top=Material.ROOF_FLAT,
                       style=sim.Style.URBAN)


def _roof_pair(sweep: SweepConfig):
    """A 30 m × 30 m roof 15 m up with a post standing 1.5 m out of it, the window on the roof."""
    world = _flat_world([[ROOF_N, 0.0, 15.0, 15.0, ROOF_H], [ROOF_N, 4.0, 1.2, 1.2, ROOF_H + POST_H]])
    return _pair(world, np.array([ROOF_N, 0.0, -ROOF_H]), sweep)


def _on(render, result, north, east, half, down):
    pts = render.geometry.points_ned[result.rows, result.cols]
    return (np.abs(pts[..., 2] - down) < 0.01) & (np.abs(pts[..., 0] - north) < half) & (np.abs(pts[..., 1] - east) < half)


def test_a_roof_is_measured_against_its_own_plane_and_what_stands_on_it_still_reads_high():
    result, render, stage = _roof_pair(ON)
    assert result.plane_raised_m == pytest.approx(ROOF_H, abs=2.5)
    roof = _on(render, result, ROOF_N, -5.0, 4.0, -ROOF_H) & np.isfinite(result.height_m)
    assert roof.sum() > 50
    h_roof, sigma = result.height_m[roof], float(np.median(result.sigma_m[roof]))
    assert sigma < 0.5 and abs(float(np.median(h_roof))) <= sigma          # the roof is the local ground
    # ... and where the roof's own texture shows it matches the roof's plane, measured well enough to confirm
    # (grass seen from 45 m at a quarter of the window's size leaves most of it unverified: no confirmation).
    assert np.isfinite(result.detectable_m[roof]).mean() > 0.1
    post = _on(render, result, ROOF_N, 4.0, 0.8, -(ROOF_H + POST_H)) & np.isfinite(result.height_m)
    assert post.sum() > 5
    # The post stands out of it by the geometry grid's rule (fusion.motion_grid: a quarter of a cell's pixels
    # at least half the obstacle height and 3 σ up marks the cell).
    h_post, s_post = result.height_m[post], result.sigma_m[post]
    assert np.mean((h_post >= 0.25) & (h_post >= 3 * s_post)) >= 0.5
    # The ground's level the stage keeps for the next windows is still the ground's, not the roof's.
    assert stage.ground_down_m is None or stage.ground_down_m == pytest.approx(0.0, abs=1.0)


def test_without_the_sweep_the_same_roof_is_not_measured():
    """Not vacuous: against the ground's plane the same pair fails on the roof (the flow's noise explodes)."""
    swept, _, _ = _roof_pair(ON)
    ground, render, _ = _roof_pair(SweepConfig(enabled=False))
    assert ground.plane_raised_m == 0.0
    roof = _on(render, ground, ROOF_N, -5.0, 4.0, -ROOF_H)
    usable = lambda res: int((roof & np.isfinite(res.detectable_m) & (res.detectable_m <= 1.0)).sum())  # noqa: E731
    assert ground.flow_noise_px > 3 * swept.flow_noise_px
    assert usable(ground) < 0.2 * usable(swept)


def test_an_alley_between_two_roofs_is_never_confirmed_as_roof():
    """A 1.5 m alley between two roofs 18 and 17.4 m up (urban seed 7101 had one): DIS smooths the roofs' flow
    over it, so its walls read as roof, placed at roof level over the gap. No pixel whose true point lies in the
    alley may confirm (here the flat roofs' faint texture leaves the roofs unconfirmed too)."""
    gap_e = (-0.75, 0.75)
    world = _blocks([[ROOF_N, gap_e[0] - 12.0, 15.0, 12.0, 18.0], [ROOF_N, gap_e[1] + 12.0, 15.0, 12.0, 17.4]])

    def in_gap(result, render):
        pts = render.geometry.points_ned[result.rows, result.cols]
        return (pts[..., 1] > gap_e[0] - 0.05) & (pts[..., 1] < gap_e[1] + 0.05) & (pts[..., 2] > -17.3)

    result, render, _ = _pair(world, np.array([ROOF_N, 0.0, -18.0]))
    assert result.plane_raised_m > 10.0
    gap = in_gap(result, render)
    assert gap.sum() > 10
    assert not np.isfinite(result.detectable_m[gap]).any()
    # Not vacuous: without the per-pixel check (every pixel taken as matching the roof's plane) the alley's
    # pixels would confirm.
    trusting = SweepConfig(enabled=True, verify_ratio=1e6, verify_margin=-1e6)
    result, render, _ = _pair(world, np.array([ROOF_N, 0.0, -18.0]), trusting)
    assert np.isfinite(result.detectable_m[in_gap(result, render)]).sum() > 5


def test_the_sweep_is_off_by_default_and_then_changes_nothing():
    assert not MotionConfig().sweep.enabled
    result, _, _ = _roof_pair(MotionConfig().sweep)
    assert result.plane_raised_m == 0.0


def test_open_ground_keeps_the_ground_plane():
    """On a flat field with nothing raised the sweep keeps the ground's level (behaviour as before)."""
    world = _flat_world([[200.0, 200.0, 1.0, 1.0, 1.0]])
    result, _, _ = _pair(world, np.array([ROOF_N, 0.0, 0.0]))
    assert result is not None and result.plane_raised_m == 0.0


def test_sweep_on_a_featureless_window_keeps_the_ground():
    """No texture, no correlation: the ground's plane stays (a level is never raised on no evidence)."""
    k = np.array([[160.0, 0.0, 159.5], [0.0, 160.0, 119.5], [0.0, 0.0, 1.0]])
    r_nc = np.array([[0.0, -0.7071, 0.7071], [1.0, 0.0, 0.0], [0.0, 0.7071, 0.7071]])
    cur = CameraPose(r_nc, np.array([0.0, 6.0, -60.0]), 60.0)
    ref = CameraPose(r_nc, np.array([0.0, -6.0, -60.0]), 60.0)
    grey = np.full((240, 320), 128, np.uint8)
    res = sweep_plane(k, cur, ref, grey, grey[100:220, 80:240], (100, 80), ON)
    assert not res.raised and res.level_m == 60.0


@pytest.mark.parametrize("bad", [dict(scale=0.0), dict(step_px=0.0), dict(max_levels=1), dict(top_share=1.0),
                                 dict(min_overlap=0.0), dict(min_gain=-0.1), dict(min_raise_m=-1.0),
                                 dict(verify_ratio=0.0)])
def test_bad_sweep_settings_are_refused(bad):
    with pytest.raises(InputError):
        SweepConfig(**bad)


def test_cells_confirmed_on_surfaces_at_different_levels_leave_a_band_between_them():
    """Each pair judges heights against its own local ground, so a roof (measured on its plane) and the street
    beside it (on the ground's) are both clear; the geometry grid leaves every cell within 1 m of a level
    change unconfirmed, so no clear disc spans the edge. A gentle slope and unconfirmed cells are no step."""
    from edge_landing.runtime.fusion.motion_grid import _level_steps

    reach = np.ones((5, 5), np.uint8)                       # 1 m at 0.5 m cells, as GeometryGrid builds it
    down = np.zeros((8, 12), np.float32)
    down[:, :6] = -18.0                                     # a roof 18 m up west of column 6
    steps = _level_steps(down, 1.2, reach)
    assert steps[:, 4:8].all() and not steps[:, :4].any() and not steps[:, 8:].any()
    slope = np.tile(np.arange(12, dtype=np.float32) * 0.08, (8, 1))   # 9°: 0.08 m per 0.5 m cell
    assert not _level_steps(slope, 1.2, reach).any()
    noisy = np.random.default_rng(0).normal(0.0, 0.17, (8, 12)).astype(np.float32)   # σ of a confirmed level
    assert _level_steps(noisy, 1.2, reach).mean() < 0.01
    hole = down.copy()
    hole[:, 6] = np.nan                                     # a hole-filled cell has no level of its own
    assert _level_steps(hole, 1.2, reach)[:, 5].all() and _level_steps(hole, 1.2, reach)[:, 7].all()
    band = down.copy()
    band[:, 5:7] = np.nan                                   # a two-cell unconfirmed band already separates them
    assert not _level_steps(band, 1.2, reach)[:, :4].any()


def test_level_steps_patched_at_cut_sides_match_a_whole_recomputation():
    """Between stage runs the geometry view reuses its level steps as the grid moves: clear cells lost at a side
    only change the cells within the kernel's reach of it, and the patched result is the whole computation's."""
    from edge_landing.runtime.fusion.geometry_memo import _level_steps, steps_at_cut_sides

    rng = np.random.default_rng(3)
    reach = np.ones((5, 5), np.uint8)
    for trial in range(40):
        down = np.where(rng.random((30, 34)) < 0.03, -18.0, rng.normal(0, 0.1, (30, 34))).astype(np.float32)
        clear = rng.random((30, 34)) < 0.7
        whole = _level_steps(np.where(clear, down, np.nan).astype(np.float32), 1.2, reach)
        r0, r1, c0, c1 = rng.integers(0, 6), 30 - rng.integers(0, 6), rng.integers(0, 6), 34 - rng.integers(0, 6)
        sub = np.s_[r0:r1, c0:c1]
        cut = (bool(clear[:r0].any()), bool(clear[r1:].any()), bool(clear[:, :c0].any()), bool(clear[:, c1:].any()))
        patched = steps_at_cut_sides(whole[sub], clear[sub], down[sub], cut, 1.2, reach)
        direct = _level_steps(np.where(clear[sub], down[sub], np.nan).astype(np.float32), 1.2, reach)
        assert np.array_equal(patched, direct), trial
