"""edge-sim --randomise (camera, palette, camera look) and the held-out rural style."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("embreex")

from edge_landing import sim  # noqa: E402
from edge_landing.evaluation.scene import Scene  # noqa: E402
from edge_landing.runtime.core.camera import Attitude, Mount, ned_from_camera  # noqa: E402
from edge_landing.sim.appearance import CameraLook, apply_look, sample_palette  # noqa: E402
from edge_landing.sim.cli import config_from_args  # noqa: E402
from edge_landing.sim.randomise import RANGES, randomised_view, scene_hfov_deg  # noqa: E402
from edge_landing.sim.world import Material  # noqa: E402

H, W = 48, 64
SEED = 11


def test_randomised_views_cover_nadir_to_oblique_and_10_to_120_m():
    world = sim.build_world("suburban", SEED)
    downs, agls = [], []
    for k in range(300):
        v = randomised_view(world, np.random.default_rng([5, k]))
        axis = ned_from_camera(Mount(), v.attitude) @ np.array([0.0, 0.0, 1.0])
        down_deg = math.degrees(math.asin(np.clip(axis[2], -1, 1)))
        assert 20.0 - 4 * RANGES.jitter_deg <= down_deg <= 90.0 + 1e-6
        assert RANGES.agl_m[0] <= v.agl_m <= RANGES.agl_m[1]
        below = world.surface_z(np.array([v.position_ned_m[0]]), np.array([v.position_ned_m[1]]))[0]
        assert below - v.position_ned_m[2] == pytest.approx(v.agl_m, abs=1e-3)
        downs.append(down_deg)
        agls.append(v.agl_m)
    assert min(downs) < 30 and max(downs) > 85 and min(agls) < 20 and max(agls) > 110
    hfovs = [scene_hfov_deg(s) for s in range(50)]
    assert 60 <= min(hfovs) < 70 and 100 < max(hfovs) <= 110


def test_randomised_scene_is_seeded_recorded_and_truth_is_untouched(tmp_path):
    cfg, _ = config_from_args([str(tmp_path / "a"), "--frames", "2", "--seed", str(SEED), "--width", str(W),
                               "--height", str(H), "--randomise"])
    assert cfg.randomise and cfg.hfov_deg == scene_hfov_deg(SEED)
    a = sim.generate(cfg, progress=False)
    b = sim.generate(sim.SimConfig(**{**cfg.__dict__, "out": tmp_path / "b"}), progress=False)
    for sub in ("rgb/000000.png", "rgb/000001.png", "depth/000001.npy", "poses.csv", "scene.json"):
        assert (a / sub).read_bytes() == (b / sub).read_bytes()
    gen = json.loads((a / "scene.json").read_text())["generator"]
    assert gen["randomise"]["hfov_deg"] == pytest.approx(cfg.hfov_deg)
    assert set(gen["randomise"]["palette"]) == {"gain", "texture_amp", "texture_cells_per_m", "object_jitter"}
    assert all("look" in f for f in gen["per_frame_effects"])
    # Ground truth: the same pose and world without --randomise gives the same depth and labels.
    plain = sim.generate(sim.SimConfig(**{**cfg.__dict__, "out": tmp_path / "c", "randomise": False}), progress=False)
    assert (plain / "rgb/000000.png").read_bytes() != (a / "rgb/000000.png").read_bytes()
    pose = Scene(a).poses()["000000"]
    assert Attitude(pose.roll_rad, pose.pitch_rad, pose.yaw_rad) != Attitude()      # the attitude carries the pitch


def test_without_the_flag_scenes_are_unchanged(tmp_path):
    cfg, _ = config_from_args([str(tmp_path / "a"), "--seed", "3"])
    assert not cfg.randomise and cfg.hfov_deg == 90.0


def test_palette_recolours_and_look_keeps_shape():
    p = sample_palette(np.random.default_rng(1))
    q = sample_palette(np.random.default_rng(2))
    assert not np.allclose(p.gain, q.gain)
    alb = np.full((4, 3), 0.5, np.float32)
    mat = np.array([Material.GRASS, Material.ASPHALT, Material.CAR_PAINT, Material.CAR_PAINT], np.uint8)
    out = p.apply(alb, mat, np.array([0, 1, 2, 500]), np.zeros((4, 3)))
    assert out.shape == (4, 3) and out.min() >= 0 and out.max() <= 1 and not np.allclose(out[2], out[3])
    img = np.full((H, W, 3), 128, np.uint8)
    look = CameraLook(white_balance=(1.1, 1.0, 0.9), vignetting=0.4, defocus_px=1.0, noise_sigma=0.01,
                      jpeg_quality=50)
    seen = apply_look(img, look, np.random.default_rng(0))
    assert seen.shape == img.shape and seen.dtype == np.uint8
    assert seen[H // 2, W // 2, 0] > seen[H // 2, W // 2, 2]             # warmer white balance
    assert seen[0, 0].mean() < seen[H // 2, W // 2].mean()               # darker corners


def test_rural_world_has_its_own_features(tmp_path):
    rural = sim.build_world("rural", SEED)
    assert {Material.CLUTTER, Material.WALL, Material.FOLIAGE} <= set(np.unique(rural.material))
    assert {Material.SOIL, Material.WATER, Material.GRASS, Material.ASPHALT} <= set(np.unique(rural.ground.cells))
    assert Material.FACADE not in set(np.unique(rural.material))           # no town blocks
    out = sim.generate(sim.SimConfig(out=tmp_path / "r", frames=2, style=sim.Style.RURAL, seed=SEED, width=W,
                                     height=H), progress=False)
    assert Scene(out).meta.generator["style"] == "rural"
    assert set(np.unique(Scene(out).read_hvo("000000"))) <= {0, 1, 2, 255}


def test_held_out_style_is_refused_for_training(tmp_path):
    from edge_landing.export.datasets import check_not_held_out

    out = sim.generate(sim.SimConfig(out=tmp_path / "r", frames=1, style=sim.Style.RURAL, seed=SEED, width=W,
                                     height=H), progress=False)
    with pytest.raises(Exception, match="held out"):
        check_not_held_out([Path(out)])
