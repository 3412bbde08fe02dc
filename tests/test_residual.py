"""What the flow left unmatched (fusion.residual): thin things DIS smooths over are still obstacle evidence, placed
where they can stand (ARCHITECTURE.md §11)."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from edge_landing.runtime.core.camera import Attitude
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.fusion.motion import CameraPose, MotionConfig
from edge_landing.runtime.fusion.residual import ResidualConfig, ray_footprints, unmatched_pixels, without_wide_regions
from tests.test_motion_evidence import MOUNT, _cell, _grid, _result


def _grass(shape: tuple[int, int], seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(90.0 + 25.0 * rng.standard_normal(shape), 0, 255).astype(np.float32)


def test_matched_images_leave_nothing_unmatched_whatever_the_gain_and_noise():
    cur = _grass((60, 80))
    rng = np.random.default_rng(1)
    matched = np.clip(0.85 * cur + 12.0 + 2.0 * rng.standard_normal(cur.shape), 0, 255)   # white balance, noise
    everywhere = np.ones(cur.shape, bool)
    assert not unmatched_pixels(cur.astype(np.uint8), matched.astype(np.uint8), everywhere, everywhere,
                                ResidualConfig()).any()


def test_a_person_two_pixels_wide_the_flow_smoothed_over_is_unmatched_and_nothing_else():
    cur, matched = _grass((60, 80)), _grass((60, 80))
    matched = cur + np.random.default_rng(2).normal(0.0, 2.0, cur.shape)
    cur[20:25, 40:42] = 30.0                 # dark clothes where the flow-warped reference still shows grass
    everywhere = np.ones(cur.shape, bool)
    odd = unmatched_pixels(np.clip(cur, 0, 255).astype(np.uint8), np.clip(matched, 0, 255).astype(np.uint8),
                           everywhere, everywhere, ResidualConfig())
    assert odd[20:25, 40:42].any()
    odd[18:27, 38:44] = False
    assert not odd.any()                     # only next to it


def test_a_pair_whose_flow_failed_is_not_checked():
    """Where the flow is pixels off, the residual is everywhere: on a noisy sensor's flight (urban 6262) such pairs
    marked a third of their windows and kept open ground an obstacle after good pairs had measured it clear."""
    cur, matched = _grass((60, 80)), _grass((60, 80))
    matched = cur + np.random.default_rng(2).normal(0.0, 2.0, cur.shape)
    cur[20:25, 40:42] = 30.0
    everywhere = np.ones(cur.shape, bool)
    u8 = (np.clip(cur, 0, 255).astype(np.uint8), np.clip(matched, 0, 255).astype(np.uint8))
    config = ResidualConfig()
    assert unmatched_pixels(*u8, everywhere, everywhere, config, flow_noise_px=config.max_flow_noise_px).any()
    assert not unmatched_pixels(*u8, everywhere, everywhere, config, flow_noise_px=1.5 * config.max_flow_noise_px).any()
    assert not unmatched_pixels(*u8, everywhere, everywhere, config, flow_noise_px=math.nan).any()
    assert config.checks(0.0) and not config.checks(0.0, 2.0) and not config.checks(0.5, 0.2)


def test_pixels_the_reference_did_not_see_are_never_unmatched_and_the_check_can_be_off():
    cur, matched = _grass((60, 80)), _grass((60, 80), seed=3)       # nothing matches anywhere
    cur[:, :40] = matched[:, :40]
    inside, usable = np.zeros(cur.shape, bool), np.zeros(cur.shape, bool)
    inside[:, :60], usable[:, :40] = True, True
    u8 = (cur.astype(np.uint8), matched.astype(np.uint8))
    odd = unmatched_pixels(*u8, usable, inside, ResidualConfig())
    assert odd[:, 45:60].mean() > 0.9 and not odd[:, 60:].any() and not odd[:, :38].any()
    assert not unmatched_pixels(*u8, usable, inside, ResidualConfig(ratio=0.0)).any()
    assert not unmatched_pixels(*u8, usable, inside, ResidualConfig(), rain_share=0.05).any()   # streaks too
    assert not unmatched_pixels(*u8, usable & (np.arange(80) < 1), inside, ResidualConfig()).any()  # too few


@pytest.mark.parametrize("field, value", [("ratio", -1.0), ("floor_grey", 0.0), ("box_px", 0), ("reach_m", -0.5),
                                          ("reach_steps", 0), ("min_pixels", 0), ("max_rain_share", -0.1),
                                          ("min_median", -0.1), ("max_flow_noise_px", 0.0),
                                          ("max_region_m", -1.0), ("region_margin_px", -1)])
def test_bad_residual_settings_name_the_value(field, value):
    with pytest.raises(InputError, match=field):
        ResidualConfig(**{field: value})


def test_ground_the_reference_did_not_show_does_not_vote_but_people_and_thin_walls_do():
    """A building between an approach keyframe and the plaza hides open ground from the reference: thousands of
    pixels in one region the flow could not match. Such a region, wider on the ground than ``max_region_m``, is
    not something thin the flow smoothed over, and its pixels (rim included) do not vote; a person (2 × 5 px)
    and a thin wall (3 px wide, 60 long) still do. Camera 50 m up, 45° down, 640×480, 90° across: at the
    window's centre 0.22 m of ground per pixel, so 3 m is 14 pixels across and 10 down."""
    pose = CameraPose.of(MOUNT, Attitude(), np.array([0.0, 0.0, -50.0]), 50.0)
    k = np.array([[320.0, 0.0, 319.5], [0.0, 320.0, 239.5], [0.0, 0.0, 1.0]])
    odd = np.zeros((120, 160), bool)
    odd[10:50, 20:80] = True                                   # the hidden ground
    odd[30:34, 80:82] = True                                   # ragged rim
    odd[70:75, 100:102] = True                                 # a person
    odd[60:63, 20:80] = True                                   # a low wall across the flight
    odd[90:110, 130:135] = True                                # a post's 1 m wide unmatched trace
    kept = without_wide_regions(odd, pose, k, (240, 180), ResidualConfig())
    assert not kept[10:50, 20:82].any()
    assert kept[70:75, 100:102].all() and kept[60:63, 20:80].all() and kept[90:110, 130:135].all()
    assert (without_wide_regions(odd, pose, k, (240, 180), ResidualConfig(max_region_m=0.0)) == odd).all()
    wider = without_wide_regions(odd, pose, k, (240, 180), ResidualConfig(max_region_m=20.0))   # 91 px across
    assert wider[10:50, 20:80].all()


def test_the_evidence_lies_along_the_ray_from_the_ground_back_to_a_persons_height():
    """Camera 50 m up, 45° down: a pixel's ground point is 50 m ahead; up to 2 m above the ground its ray is
    2 m nearer the camera (tan 45°). A raised local ground (0.5 m above the plane) moves them all nearer."""
    pose = CameraPose.of(MOUNT, Attitude(), np.array([0.0, 0.0, -50.0]), 50.0)
    centre = np.zeros((2, 1))                                                  # the optical axis
    ne = ray_footprints(pose, centre, np.zeros(1), ResidualConfig())
    assert ne.shape == (9, 2)
    np.testing.assert_allclose(ne[:, 1], 0.0, atol=1e-4)
    np.testing.assert_allclose(np.sort(ne[:, 0]), np.linspace(48.0, 50.0, 9), atol=1e-3)
    raised = ray_footprints(pose, centre, np.array([0.5]), ResidualConfig())
    assert math.isclose(float(raised[:, 0].max()), 49.5, abs_tol=1e-3)


def test_unmatched_pixels_vote_a_cell_seen_unmatched_by_one_pair_in_ten_stays_clear_by_most_an_obstacle():
    """Open ground has a few unmatched pixels in some pairs, a person in most: they vote with the high ones
    (``obstacle_vote_share``) and never revoke a confirmation by themselves."""
    grid = _grid()
    shape = (20, 20)
    zeros, none = np.zeros(shape), np.zeros(shape, bool)
    spot = np.array([[7.6, 7.6]], np.float32)
    cell, beside = _cell(grid, 7.6, 7.6), _cell(grid, 6.1, 6.1)

    def frame(t: float, unmatched: bool) -> None:   # level ground measured to 0.3 m: only the unmatched points differ
        grid.add(replace(_result(zeros, np.full(shape, 0.3), none, t), unmatched_ne_m=spot if unmatched else None))

    for k in range(10):
        frame(0.2 * k, unmatched=k == 9)
    view = grid.view(grid.north0_m, grid.east0_m, (grid.size, grid.size), 1.8)
    assert view.clear[cell] and not view.obstacle[cell]
    for k in range(10, 16):
        frame(0.2 * k, unmatched=True)
    view = grid.view(grid.north0_m, grid.east0_m, (grid.size, grid.size), 3.0)
    assert view.obstacle[cell] and not view.clear[cell]
    assert view.clear[beside] and not view.obstacle[beside]


sim = pytest.importorskip("edge_landing.sim", reason="the sim extra (embreex) renders the test worlds")


def test_people_with_contrast_against_the_grass_are_obstacles_from_50_m():
    """Four people (0.45 × 0.28 m, 1.7 m tall, dark blue) 4 m around a spot 30 m ahead, 50 m up, at 640×480. DIS
    reads them at 0-0.3 m: without the residual check their cells were confirmed clear. Three stand on grass
    they differ from by 35-45 grey levels; the one on dark grass (35 against 46) is seen in colour only, and
    partly (the strict expected failure in test_motion)."""
    from tests.test_motion import Material, _cells_within, _flat_world, _fly_over, _open_share

    centre = np.array([30.0, 0.0, 0.0])
    people = [[centre[0] + dn, de, 0.225, 0.14, 1.7] for dn, de in ((0.0, 4.0), (-4.0, 0.0), (4.0, 0.0))]
    world = _flat_world(people, side=Material.CLUTTER, tint=(0.15, 0.18, 0.35), top=Material.CLUTTER)
    grid, view = _fly_over(world, centre, 50.0)
    assert _open_share(grid, view, people, centre) > 0.5
    for n, e, hn, he, _ in people:
        cells = _cells_within(grid, n, e, hn, he)
        assert view.obstacle[cells].all() and not view.clear[cells].any(), (n, e)
    config = MotionConfig()
    grid, view = _fly_over(world, centre, 50.0, replace(config, residual=replace(config.residual, ratio=0.0)))   # off
    assert all(view.clear[_cells_within(grid, n, e, hn, he)].any() for n, e, hn, he, _ in people)


def test_a_person_of_the_grass_s_grey_is_unmatched_in_colour_only():
    """Red clothes whose grey equals the green grass's: the grey residual sees nothing, Cr does (fusion.chroma)."""
    import cv2

    from edge_landing.runtime.fusion.chroma import ChromaMaker, chroma_unmatched

    rng = np.random.default_rng(4)
    shade = np.clip(1.0 + 0.03 * rng.standard_normal((120, 160, 1)), 0.3, 2.0)   # lawn: little texture in grey
    grass = np.clip(shade * np.array([70.0, 110.0, 40.0]), 0, 255).astype(np.uint8)
    cur = grass.copy()
    cur[50:60, 80:84] = (175, 55, 55)                         # grey 0.299·175 + 0.587·55 + 0.114·55 = 91 ≈ grass
    cur, grass = (np.clip(im + rng.normal(0.0, 2.0, im.shape), 0, 255).astype(np.uint8) for im in (cur, grass))  # noise
    grey_c, grey_g = cv2.cvtColor(cur, cv2.COLOR_RGB2GRAY), cv2.cvtColor(grass, cv2.COLOR_RGB2GRAY)
    assert abs(float(grey_c[50:60, 80:84].mean()) - float(grey_g[45:65, 70:94].mean())) < 2
    everywhere = np.ones((120, 160), bool)
    config = ResidualConfig()
    assert not unmatched_pixels(grey_c, grey_g, everywhere, everywhere, config)[50:60, 80:84].any()
    maker = ChromaMaker(np.array([[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]]), None, (120, 160))
    yy, xx = np.mgrid[0:120, 0:160].astype(np.float32)
    window, still = (slice(0, 120), slice(0, 160)), (xx, yy)      # no flow: each pixel matches itself
    odd = chroma_unmatched(maker(cur), maker(grass), np.eye(3), window, still, everywhere, everywhere, config)
    assert odd[50:60, 80:84].any()
    assert not chroma_unmatched(maker(cur), maker(grass), np.eye(3), window, still, everywhere, everywhere, config,
                                flow_noise_px=2.0).any()     # a pair whose flow failed is not checked in colour either
    odd[46:64, 76:88] = False
    assert not odd.any()
    assert maker(grey_c) is None                              # a grey camera: no colour to compare


def test_ground_of_one_colour_is_not_unmatched_by_its_quantisation():
    """Asphalt's chroma is one level everywhere: its residual's median is ~0, and 4 x that took the odd level of
    rounding for a mismatch on a fifth of urban windows (urban 7303: every target lost) until the median was
    floored (``min_median``). A real mismatch (a person's colour, 15 levels) still stands out."""
    rng = np.random.default_rng(5)
    cur = np.full((60, 80), 128, np.uint8)
    flips = rng.random(cur.shape) < 0.03                       # rounding: a level off here and there
    matched = np.where(flips, 129, 128).astype(np.uint8)
    cur[20:25, 40:42] = 143
    everywhere = np.ones(cur.shape, bool)
    odd = unmatched_pixels(cur, matched, everywhere, everywhere, ResidualConfig(), floor_grey=2.0)
    assert odd[20:25, 40:42].any()
    odd[18:27, 38:44] = False
    assert not odd.any()
    floorless = unmatched_pixels(cur, matched, everywhere, everywhere, ResidualConfig(min_median=0.0), floor_grey=2.0)
    assert floorless.mean() > 0.02                             # what the floor prevents
