"""edge-sim: geometric truth of the rendered scenes, determinism, flight video, live camera and CLI errors."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("embreex")

from edge_landing import sim  # noqa: E402
from edge_landing.evaluation.scene import Scene  # noqa: E402
from edge_landing.runtime.core.camera import (  # noqa: E402
    Attitude,
    Intrinsics,
    Mount,
    ned_from_camera,
    up_in_camera,
)
from edge_landing.runtime.core.geometry import HORIZONTAL, OTHER, hvo_from_normals, normals_from_depth  # noqa: E402
from edge_landing.sim.cli import config_from_args  # noqa: E402
from edge_landing.sim.cli import main as sim_main  # noqa: E402
from edge_landing.sim.world import NOT_GROUND, LabelRule, Material  # noqa: E402

H, W = 60, 80
SEED = 11          # one seed for most tests: each world is built once per process (cached)


@pytest.fixture(scope="module", params=["suburban", "urban"])
def scene_dir(request, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp(f"sim_{request.param}") / "scene"
    # The geometric labels: the test below derives them from the depth's normals.
    sim.generate(sim.SimConfig(out=out, frames=4, style=sim.Style.from_string(request.param), seed=SEED,
                               width=W, height=H, labels=LabelRule.GEOMETRY), progress=False)
    return out


def _world_points(scene: Scene, fid: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Back-project a frame's depth with scene.json intrinsics and the poses.csv pose: (points NED, R, origin)."""
    pose = scene.poses()[fid]
    rot = ned_from_camera(scene.meta.mount, Attitude(pose.roll_rad, pose.pitch_rad, pose.yaw_rad))
    cam = scene.meta.intrinsics.backproject(scene.read_depth(fid)).astype(np.float64)
    return cam @ rot.T + np.asarray(pose.ned_m), rot, np.asarray(pose.ned_m)


def test_backprojected_depth_lies_on_the_rendered_surfaces(scene_dir):
    scene = Scene(scene_dir)
    world = sim.build_world(scene.meta.generator["style"], scene.meta.generator["seed"])
    for fid in scene.frame_ids:
        pts, rot, _ = _world_points(scene, fid)
        n_world = scene.read_normals(fid).astype(np.float64) @ rot.T
        ok = np.isfinite(pts[..., 0])
        assert ok.mean() > 0.9
        # Re-cast a ray from 0.5 m off the surface, back along the normal: it must hit 0.5 m away.
        p, n = pts[ok], n_world[ok] / np.linalg.norm(n_world[ok], axis=1, keepdims=True)
        t, tri = world.intersect(p + 0.5 * n, -n)
        assert np.all(tri >= 0)
        err = np.abs(t - 0.5)
        assert np.median(err) < 2e-3 and np.mean(err < 0.02) > 0.99, (fid, np.percentile(err, [50, 99]))


def test_normals_and_labels_agree_with_depth_on_interior_pixels(scene_dir):
    from scipy.ndimage import binary_erosion

    scene = Scene(scene_dir)
    up = None
    agree_n, agree_l, total = 0, 0, 0
    for fid, pose in scene.poses().items():
        intr = scene.meta.intrinsics
        normals = scene.read_normals(fid)
        up = up_in_camera(scene.meta.mount, Attitude(pose.roll_rad, pose.pitch_rad, pose.yaw_rad))
        from_depth = normals_from_depth(scene.read_depth(fid), intr)
        labels = scene.read_hvo(fid)
        # Interior: the stored normal is the same over the 3×3 neighbourhood (one planar surface).
        same = np.ones(labels.shape, bool)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                same &= np.sum(normals * np.roll(normals, (dy, dx), axis=(0, 1)), axis=-1) > math.cos(math.radians(1))
        interior = binary_erosion(same, iterations=1, border_value=0) & np.isfinite(from_depth[..., 0])
        cos = np.sum(from_depth[interior] * normals[interior], axis=-1)
        agree_n += int(np.sum(cos > math.cos(math.radians(3.0))))
        derived = hvo_from_normals(from_depth, up, scene.meta.hvo_thresholds)
        agree_l += int(np.sum(derived[interior] == labels[interior]))
        total += int(interior.sum())
    assert total > 1000
    assert agree_n / total > 0.97, agree_n / total
    assert agree_l / total > 0.97, agree_l / total


def test_labels_match_the_recipe_and_sky_is_nan_and_255():
    world = sim.build_world("suburban", SEED)
    renderer = sim.Renderer(world, Intrinsics.from_hfov(W, H))
    view = sim.random_view(world, np.random.default_rng(3))
    # Nose up 40°: the camera looks 5° above the horizon, so the upper part of the image is sky.
    att = Attitude(0.0, math.radians(40.0), view.attitude.yaw_rad)
    out = renderer.render(view.position_ned_m, att, sim.Effects(), np.random.default_rng(0))
    g = out.geometry
    sky = ~np.isfinite(g.depth_m)
    assert 0.1 < sky.mean() < 0.9
    assert np.all(g.hvo[sky] == 255) and np.all(np.isnan(g.normals[sky])) and np.all(g.material[sky] == 255)
    assert np.all(g.hvo[~sky] != 255) and np.all(g.depth_m[~sky] > 0)
    assert np.mean(out.rgb[sky][:, 2]) > np.mean(out.rgb[sky][:, 0])          # sky is blue-ish
    expected = hvo_from_normals(g.normals, up_in_camera(Mount(), att)) | (sky * 255).astype(np.uint8)
    expected[np.isin(g.material, NOT_GROUND)] = OTHER         # the default (landing) rule: see the test below
    assert np.array_equal(g.hvo, expected)
    # Normals face the camera.
    assert np.all(np.sum(g.normals[~sky] * Intrinsics.from_hfov(W, H).pixel_rays()[~sky], axis=-1) < 0)


def test_trees_cars_clutter_and_water_are_never_horizontal_under_the_landing_rule():
    """A tree crown's top, a car roof and a pond face up: the paper's geometric rule calls them horizontal, the
    default landing rule calls them other; every other pixel is labelled the same by both."""
    world = sim.build_world("suburban", 7101, hazards=True)
    intr = Intrinsics.from_hfov(160, 120)
    rules = {rule: sim.Renderer(world, intr, labels=rule) for rule in LabelRule}
    up_not_ground, n_not_ground = 0, 0
    for k in range(4):
        view = sim.random_view(world, np.random.default_rng(100 + k))
        g = {rule: r.geometry(view.position_ned_m, view.attitude) for rule, r in rules.items()}
        landing, geometric = g[LabelRule.LANDING], g[LabelRule.GEOMETRY]
        kind = np.isin(landing.material, NOT_GROUND)
        assert not np.any(landing.hvo[kind] == HORIZONTAL)
        assert np.all(landing.hvo[kind] == OTHER)
        assert np.array_equal(landing.hvo[~kind], geometric.hvo[~kind])
        up_not_ground += int(np.sum(geometric.hvo[kind] == HORIZONTAL))
        n_not_ground += int(kind.sum())
    assert n_not_ground > 500 and up_not_ground > 50, (n_not_ground, up_not_ground)   # not vacuous


def test_the_label_rule_is_recorded_and_a_bad_one_is_refused(tmp_path, capsys):
    out = tmp_path / "geo"
    assert sim_main([str(out), "--frames", "1", "--width", "40", "--height", "30", "--labels", "geometry",
                     "--quiet"]) == 0
    assert Scene(out).meta.generator["labels"] == "geometry"
    assert sim_main([str(tmp_path / "bad"), "--frames", "1", "--labels", "semantic", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--labels: unsupported label rule 'semantic'" in err[0], err


def test_views_are_30_to_90_m_up_with_the_camera_45_degrees_down():
    world = sim.build_world("urban", SEED)
    r45 = math.sin(math.radians(45.0))
    agls = []
    for k in range(200):
        v = sim.random_view(world, np.random.default_rng([7, k]))
        assert 30.0 <= v.agl_m <= 90.0
        below = world.surface_z(np.array([v.position_ned_m[0]]), np.array([v.position_ned_m[1]]))[0]
        assert below - v.position_ned_m[2] == pytest.approx(v.agl_m, abs=1e-3)
        axis = ned_from_camera(Mount(), v.attitude) @ np.array([0.0, 0.0, 1.0])
        assert axis[2] == pytest.approx(r45, abs=1e-9)                         # optical axis 45° below horizon
        assert v.attitude.roll_rad == 0.0 and v.attitude.pitch_rad == 0.0
        agls.append(v.agl_m)
    assert min(agls) < 40 and max(agls) > 80


def test_scene_files_follow_the_contract(scene_dir):
    scene = Scene(scene_dir)
    meta = scene.meta
    assert (meta.intrinsics.width, meta.intrinsics.height) == (W, H)
    assert meta.mount.pitch_rad == pytest.approx(-math.pi / 4)
    assert meta.frame_count == 4 and len(scene) == 4
    gen = meta.generator
    assert gen["name"] == "edge-sim" and gen["seed"] == SEED and gen["version"] == sim.__version__
    assert len(gen["per_frame_effects"]) == 4 and "effects" in gen
    for fid in scene.frame_ids:
        assert scene.read_rgb(fid).shape == (H, W, 3)
        d = np.load(scene_dir / "depth" / f"{fid}.npy")
        assert d.dtype == np.float32 and d.shape == (H, W)
        assert set(np.unique(scene.read_hvo(fid))) <= {0, 1, 2, 255}
        assert np.load(scene_dir / "normals" / f"{fid}.npy").dtype == np.float16
    poses = scene.poses()
    assert [p.t_s for p in poses.values()] == pytest.approx([0.0, 0.1, 0.2, 0.3])


def test_same_seed_gives_identical_files_and_styles_differ(tmp_path):
    def files(root: Path) -> dict:
        return {p.relative_to(root): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}

    cfg = dict(frames=2, style=sim.Style.URBAN, seed=SEED, width=W, height=H)
    a = files(sim.generate(sim.SimConfig(out=tmp_path / "a", **cfg), progress=False))
    b = files(sim.generate(sim.SimConfig(out=tmp_path / "b", **cfg), progress=False))
    assert a == b and len(a) >= 9
    c = files(sim.generate(sim.SimConfig(out=tmp_path / "c", **{**cfg, "seed": SEED + 1}), progress=False))
    assert c[Path("rgb/000000.png")] != a[Path("rgb/000000.png")]


def test_worlds_have_the_style_features():
    sub, urb = sim.build_world("suburban", SEED), sim.build_world("urban", SEED)
    assert {Material.ROOF_TILE, Material.WALL, Material.FOLIAGE, Material.CAR_PAINT} <= set(np.unique(sub.material))
    assert {Material.FACADE, Material.ROOF_FLAT, Material.CLUTTER, Material.CAR_PAINT} <= set(np.unique(urb.material))
    assert sim.build_world("suburban", SEED) is sub                                # cached
    assert np.abs(sub.terrain.z).max() < 5.0                                   # ground near z = 0
    assert set(np.unique(sub.ground.cells)) >= {Material.GRASS, Material.ASPHALT, Material.MARKING, Material.CONCRETE}


def test_people_stand_around_the_spots_and_leave_the_world_otherwise_as_it_was():
    """lying_model --people: person-sized boxes (0.45 × 0.28 m, 1.5-1.9 m) on the ground 6-25 m from each
    landing spot; the town and its hazards are the same triangles as without them."""
    from edge_landing.sim.hazards import PeopleConfig

    plain, crowd = sim.build_world("suburban", SEED, hazards=True), sim.build_world("suburban", SEED, hazards=True,
                                                                                     people=True)
    added = crowd.tris[len(plain.tris):]
    assert np.array_equal(crowd.tris[:len(plain.tris)], plain.tris)
    per_person = 10                                           # a box: 5 faces (no floor) of 2 triangles
    assert len(added) == per_person * PeopleConfig().per_spot * len(plain.landing_spots)
    cfg = PeopleConfig()
    for k, person in enumerate(added.reshape(-1, per_person, 3, 3)[:50]):
        pts = person.reshape(-1, 3)
        centre = pts[:, :2].mean(axis=0)
        extent = pts[:, :2].max(axis=0) - pts[:, :2].min(axis=0)
        assert 0.28 <= extent.min() and extent.max() <= 0.45 * math.sqrt(2) + 1e-3     # any yaw
        ground = plain.terrain.z_at_point(*centre)
        assert 1.5 - 1e-3 <= ground - pts[:, 2].min() <= 1.9 + 1e-3                     # standing on the terrain
        own_spot = plain.landing_spots[k // cfg.per_spot]                 # placed spot by spot, in order
        assert cfg.keep_clear_m - 1e-3 <= np.hypot(*(own_spot - centre)) <= cfg.ring_m + 1e-3


def test_flight_writes_a_video_and_descends(tmp_path):
    import cv2

    out = sim.generate(sim.SimConfig(out=tmp_path / "f", frames=12, seed=SEED, width=64, height=48, flight=True,
                                     preview=True), progress=False)
    cap = cv2.VideoCapture(str(out / "flight.mp4"))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == 12
    poses = list(Scene(out).poses().values())
    assert poses[-1].agl_m < poses[0].agl_m - 30 and poses[-1].agl_m > 5
    assert (out / "preview.png").stat().st_size > 0
    # The live camera flies the same flight: its first frame is the scene's first frame.
    rgb, pose, _ = sim.SimCamera(style="suburban", seed=SEED, width=64, height=48, flight_frames=12).read()
    assert np.array_equal(rgb, Scene(out).read_rgb("000000")) and pose.ned_m == pytest.approx(poses[0].ned_m)


def test_a_flight_too_short_for_a_multirotor_says_so(caplog):
    """The approach covers ~110 m whatever --frames says: 60 frames at 10 frames/s fly it at ~70 m/s, which
    edge-run refuses as position jumps; the default 200 stay near 20 m/s and say nothing."""
    import logging

    from edge_landing.sim.flight import peak_speed_mps
    from edge_landing.sim.generate import vehicle_samples

    world = sim.build_world(sim.Style.SUBURBAN, SEED)
    with caplog.at_level(logging.WARNING, logger="edge_landing.sim.generate"):
        short = list(vehicle_samples(sim.SimConfig(out=Path("x"), frames=60, seed=SEED, flight=True), world))
        assert peak_speed_mps(short) > 40.0 and len(caplog.records) == 1
        assert "frames or more keep it under 25 m/s" in caplog.records[0].getMessage()
        usual = list(vehicle_samples(sim.SimConfig(out=Path("x"), frames=200, seed=SEED, flight=True), world))
    assert peak_speed_mps(usual) < 25.0 and len(caplog.records) == 1


def test_an_arc_approach_turns_the_direction_of_flight_and_ends_where_the_straight_one_does(tmp_path):
    """Same spot, hover and descent; the approach bends up to 25 m sideways with the camera turned to the spot,
    so the direction of flight (and the pairs' epipolar lines) turns; the straight flight is the default."""
    from edge_landing.sim.flight import ARC_OFFSET_M, peak_speed_mps
    from edge_landing.sim.generate import vehicle_samples

    world = sim.build_world(sim.Style.SUBURBAN, SEED)
    straight = list(vehicle_samples(sim.SimConfig(out=Path("x"), frames=200, seed=SEED, flight=True), world))
    arc = list(vehicle_samples(sim.SimConfig(out=Path("x"), frames=200, seed=SEED, flight=True,
                                             approach=sim.Approach.ARC), world))
    n_app = 80
    for a, b in zip(straight[n_app:], arc[n_app:]):                  # hover and descent: the same poses
        assert np.array_equal(a.position_ned_m, b.position_ned_m) and a.attitude == b.attitude
    p_s = np.array([s.position_ned_m[:2] for s in straight[:n_app]])
    p_a = np.array([s.position_ned_m[:2] for s in arc[:n_app]])
    line = (p_s[-1] - p_s[0]) / np.linalg.norm(p_s[-1] - p_s[0])
    side = np.abs((p_a - p_s) @ np.array([-line[1], line[0]]))
    assert side.max() == pytest.approx(ARC_OFFSET_M, abs=0.5) and side[0] < 1e-6 and side[-1] < 1e-6
    steps = np.diff(p_a, axis=0)
    turn_deg = np.degrees(np.arctan2(steps[:, 1], steps[:, 0]) - math.atan2(line[1], line[0]))
    assert turn_deg.max() > 25 and turn_deg.min() < -25                # from one side of the line to the other
    spot = straight[-1].position_ned_m[:2]                              # the descent ends above the spot's line
    for s in arc[:n_app:10]:                                            # the camera looks towards the spot
        to_spot = math.atan2(*(spot - s.position_ned_m[:2])[::-1])
        off = math.remainder(s.attitude.yaw_rad - to_spot, 2 * math.pi)
        assert abs(math.degrees(off)) < 3.0
    assert peak_speed_mps(arc) < 25.0
    gen = json.loads((sim.generate(sim.SimConfig(out=tmp_path / "a", frames=2, seed=SEED, width=32, height=24,
                                                 flight=True, approach=sim.Approach.ARC), progress=False)
                      / "scene.json").read_text())["generator"]
    assert gen["approach"] == "arc"


def test_sim_camera_reads_frames_with_pose_and_state():
    cam = sim.SimCamera(style="suburban", seed=SEED, width=64, height=48, fps=5.0, flight_frames=4)
    times = []
    for _ in range(5):                                   # runs past the flight's end: it restarts
        rgb, pose, state = cam.read()
        assert rgb.shape == (48, 64, 3) and rgb.dtype == np.uint8
        assert state.time_s == pose.t_s and state.agl_m == pose.agl_m and state.agl_source == "sim"
        times.append(state.time_s)
    assert np.all(np.diff(times) == pytest.approx(0.2))
    truth = cam.read_truth()
    assert truth.geometry.depth_m.shape == (48, 64)


@pytest.mark.parametrize("args, needle", [
    (["--frames", "-3"], "--frames must be at least 1"),
    (["--style", "desert"], "unsupported world style 'desert'"),
    (["--rain", "2"], "--rain must be between 0 and 1"),
    (["--frames", "two"], "invalid int value"),
    (["--approach", "zigzag"], "--approach: unsupported approach 'zigzag'"),
    (["--approach", "arc"], "--approach arc needs --flight"),
])
def test_bad_arguments_give_one_clear_line(tmp_path, capsys, args, needle):
    code = sim_main([str(tmp_path / "out"), *args, "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and needle in err[0], err


def test_unwritable_output_is_a_clear_error(tmp_path, capsys):
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    assert sim_main([str(blocker / "scene"), "--frames", "1", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "scene" in err[0]
    assert sim_main([str(blocker), "--frames", "1", "--quiet"]) == 2
    assert "not a folder" in capsys.readouterr().err


def test_cli_writes_a_scene_and_refuses_to_clobber_it(tmp_path, capsys):
    out = tmp_path / "cli"
    assert sim_main([str(out), "--frames", "1", "--width", "40", "--height", "30", "--seed", str(SEED), "--clear",
                     "--quiet"]) == 0
    assert Scene(out).meta.generator["effects"]["rain"] == 0.0
    assert sim_main([str(out), "--frames", "1", "--width", "40", "--height", "30", "--quiet"]) == 2
    assert "--overwrite" in capsys.readouterr().err


def test_effects_change_the_image_but_never_the_ground_truth():
    world = sim.build_world("suburban", SEED)
    renderer = sim.Renderer(world, Intrinsics.from_hfov(W, H))
    view = sim.random_view(world, np.random.default_rng(8))
    clean = sim.Effects(haze_per_m=0.0, noise_sigma=0.0)
    foggy = sim.Effects(haze_per_m=0.01, rain=0.8, motion_blur_px=5.0, noise_sigma=0.02, exposure_ev=0.5)
    a = renderer.render(view.position_ned_m, view.attitude, clean, np.random.default_rng(0))
    b = renderer.render(view.position_ned_m, view.attitude, foggy, np.random.default_rng(0))
    for name in ("depth_m", "normals", "hvo", "material"):
        assert np.array_equal(getattr(a.geometry, name), getattr(b.geometry, name), equal_nan=name != "hvo")
    # Fog washes distant pixels out: less contrast in the far (top) rows.
    assert b.rgb[: H // 4].std() < a.rgb[: H // 4].std()
    # The sun sets the shading: lit and shadowed views of one pose differ.
    low_sun = sim.Effects(haze_per_m=0.0, noise_sigma=0.0, sun_elevation_rad=math.radians(10.0))
    c = renderer.render(view.position_ned_m, view.attitude, low_sun, np.random.default_rng(0))
    assert np.mean(np.abs(c.rgb.astype(int) - a.rgb.astype(int))) > 5


def test_effect_overrides_fix_values_and_the_rest_stay_seeded():
    fixed = sim.EffectOverrides(rain=0.0, noise_sigma=0.005)
    draws = [sim.sample_effects(np.random.default_rng(k), fixed) for k in range(20)]
    assert all(d.rain == 0.0 and d.noise_sigma == 0.005 for d in draws)
    assert len({d.sun_azimuth_rad for d in draws}) == 20
    assert sim.sample_effects(np.random.default_rng(3)) == sim.sample_effects(np.random.default_rng(3))
    assert all(15.0 <= math.degrees(d.sun_elevation_rad) <= 75.0 for d in draws)


def test_people_are_a_recorded_choice_of_the_scene(tmp_path):
    """edge-sim --people renders the people of lying_model --people and says so in scene.json, where
    landing_truth reads which world to judge in."""
    args = ["--frames", "1", "--seed", str(SEED), "--width", str(W), "--height", str(H), "--hazards"]
    gens = {}
    for people in (False, True):
        cfg, _ = config_from_args([str(tmp_path / str(people)), *args, *(["--people"] if people else [])])
        assert cfg.people is people
        gens[people] = json.loads((sim.generate(cfg, progress=False) / "scene.json").read_text())["generator"]
        assert gens[people]["people"] is people and gens[people]["hazards"] is True
    assert gens[True]["world"]["triangles"] > gens[False]["world"]["triangles"]
