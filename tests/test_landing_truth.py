"""The ground-truth landing checker really tells safe from unsafe spots (sim world geometry)."""
import json

import numpy as np
import pytest

pytest.importorskip("embreex")

from edge_landing import sim  # noqa: E402
from edge_landing.benchmarks.landing_truth import TruthConfig, check_target, evaluate, main  # noqa: E402


@pytest.fixture(scope="module")
def world():
    return sim.build_world("suburban", 0)


def run_header(style, seed, camera="sim", source_kind="sim"):
    """The first line edge-run --log writes: where the frames came from."""
    return {"run": {"version": "0.2.0", "camera": camera, "source_kind": source_kind, "sim_style": style,
                    "sim_seed": seed, "poses": None, "model": "edgenet.onnx", "autopilot": "ardupilot"}}


def open_spot(world):
    """An open landing spot of the generator well inside the world's edge."""
    spots = world.landing_spots[np.abs(world.landing_spots).max(axis=1) < 400]
    return spots[0]


def test_open_ground_passes_and_a_pitched_roof_fails(world, tmp_path):
    cfg = TruthConfig(log="", clearance_m=2.0)
    n, e = open_spot(world)
    assert check_target(world, n, e, cfg) == (True, "ok")
    tilt = np.degrees(np.arccos(np.abs(world.normals[:, 2])))
    inside = np.abs(world.tris[:, :, :2]).max(axis=(1, 2)) < 400
    pitched = (world.material == sim.world.Material.ROOF_TILE) & (tilt > 20) & (tilt < 60) & inside
    roof = np.flatnonzero(pitched)[0]                                 # a pitched roof face of a house
    n, e = world.tris[roof].mean(axis=0)[:2]
    ok, why = check_target(world, n, e, cfg)
    assert not ok and ("tilted" in why or "step" in why)
    log = tmp_path / "t.jsonl"
    ln, le = open_spot(world)
    log.write_text("\n".join(json.dumps(r) for r in (
        run_header("suburban", 0),
        {"frame": 0, "valid": True, "ned_m": [float(ln), float(le), 0.0]},
        {"frame": 1, "valid": True, "ned_m": [float(n), float(e), 0.0]},
        {"frame": 2, "valid": False, "ned_m": None})) + "\n")
    result = evaluate(TruthConfig(log=str(log)))
    assert (result["targets"], result["safe"]) == (2, 1) and result["failures"][0]["frame"] == 1


def write_log(path, header, ned):
    lines = ([header] if header else []) + [{"frame": 0, "valid": True, "ned_m": [float(ned[0]), float(ned[1]), 0.0]}]
    path.write_text("\n".join(json.dumps(r) for r in lines) + "\n")
    return path


def test_the_world_comes_from_the_log_header_and_flags_override_it(world, tmp_path, capsys):
    n, e = open_spot(world)               # open ground in suburban seed 0
    log = write_log(tmp_path / "sub.jsonl", run_header("suburban", 0), (n, e))
    result = evaluate(TruthConfig(log=str(log)))
    assert result["world"] == {"style": "suburban", "seed": 0, "hazards": False, "people": False,
                               "from": "the log header"}
    assert (result["frames"], result["targets"], result["safe"]) == (1, 1, 1)   # the header is not a decision
    # the same spot judged in a log that says urban seed 3: another world, so it is judged there
    urban = write_log(tmp_path / "urban.jsonl", run_header("urban", 3), (n, e))
    assert evaluate(TruthConfig(log=str(urban)))["world"] == {"style": "urban", "seed": 3, "hazards": False,
                                                              "people": False, "from": "the log header"}
    # explicit flags win over the header
    assert main([str(urban), "--style", "suburban", "--seed", "0"]) == 0
    assert "1/1 targets" in capsys.readouterr().out
    over = evaluate(TruthConfig(log=str(urban), style="suburban", seed=0))
    assert over["world"] == {"style": "suburban", "seed": 0, "hazards": False, "people": False,
                             "from": "--style/--seed and the log header"} and over["safe"] == 1


def test_a_log_that_names_no_world_is_refused_in_one_line(world, tmp_path, capsys):
    n, e = open_spot(world)
    bare = write_log(tmp_path / "old.jsonl", None, (n, e))
    assert main([str(bare)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no run header" in err[0] and "--style and --seed" in err[0]
    assert main([str(bare), "--style", "suburban"]) == 2          # half a world is no world: no default seed
    assert "--seed" in capsys.readouterr().err
    assert main([str(bare), "--style", "suburban", "--seed", "0"]) == 0
    video = write_log(tmp_path / "video.jsonl", run_header(None, None, "flight.mp4", "video"), (n, e))
    assert main([str(video)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "flight.mp4" in err[0] and "not a known sim world" in err[0]
    assert main([str(video), "--style", "suburban", "--seed", "0"]) == 0


def test_a_replayed_edge_sim_video_is_judged_in_the_world_its_scene_json_names(world, tmp_path, capsys):
    """--poses or --tlog replays of an edge-sim --flight video: the scene.json beside the video names the world,
    hazards included (judged without them, a spot by a car would pass); one that does not say is refused."""
    n, e = open_spot(world)
    scene = tmp_path / "scene"
    scene.mkdir()
    video = scene / "flight.mp4"
    video.write_bytes(b"")
    log = write_log(tmp_path / "replay.jsonl", run_header(None, None, str(video), "file"), (n, e))
    for hazards, people in ((False, False), (True, False), (True, True)):
        generator = {"name": "edge-sim", "style": "suburban", "seed": 0, "hazards": hazards, "people": people}
        (scene / "scene.json").write_text(json.dumps({"generator": generator}))
        assert evaluate(TruthConfig(log=str(log)))["world"] == {"style": "suburban", "seed": 0, "hazards": hazards,
                                                                "people": people, "from": str(scene / "scene.json")}
    assert main([str(log)]) == 0 and "seed 0 with hazards and people (from" in capsys.readouterr().out
    assert main([str(log), "--no-people"]) == 0 and "seed 0 with hazards (from" in capsys.readouterr().out
    (scene / "scene.json").write_text(json.dumps({"generator": {"name": "edge-sim", "style": "suburban", "seed": 0}}))
    assert main([str(log)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--hazards or --no-hazards" in err[0]
    assert main([str(log), "--no-hazards"]) == 0


def test_a_sim_follow_log_is_judged_about_the_autopilots_home(world, tmp_path):
    """sim-follow targets are in the autopilot's local NED: the home's place in the world is added. The home lies
    on open level ground, so a target at local (0, 0) is safe; judged in the world's own frame it is elsewhere."""
    from edge_landing.sim.follow import place_home

    home = place_home(world)
    log = tmp_path / "t.jsonl"
    record = {"frame": 0, "capture_time_s": 0.0, "valid": True, "ned_m": [0.0, 0.0, 0.0]}
    log.write_text(json.dumps(run_header("suburban", 0, "sim-follow:suburban:0", "sim-follow")) + "\n"
                   + json.dumps(record) + "\n")
    report = evaluate(TruthConfig(log=str(log), clearance_m=2.0))
    assert (report["targets"], report["safe"]) == (1, 1)
    assert np.hypot(*home[:2]) > 5.0                                  # the offset is not a no-op here


def _inside(world, material, margin_m: float = 6.0) -> np.ndarray:
    """Ground points (n, e) at least ``margin_m`` inside a patch of ``material`` (a 2 m disc lands on it only)."""
    g = np.arange(-200.0, 200.0, 2.0)
    n, e = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    keep = np.ones(n.shape, dtype=bool)
    for dn in (-margin_m, 0.0, margin_m):
        for de in (-margin_m, 0.0, margin_m):
            keep &= world.ground.lookup(n + dn, e + de) == material
    return np.stack([n[keep], e[keep]], axis=-1)


def test_level_water_is_no_landing_spot_but_level_soil_beside_it_is():
    """Water is level and horizontal by its normals (the paper's labels): only its material makes it unsafe."""
    rural = sim.build_world("rural", 7202, hazards=True)
    Material = sim.world.Material
    water = _inside(rural, Material.WATER)
    assert len(water) > 0, "the rural world has a canal and ponds"
    cfg = TruthConfig(log="", clearance_m=2.0)
    assert check_target(rural, *water[0], cfg) == (False, "water inside the disc")
    verdicts = [check_target(rural, *p, cfg) for p in _inside(rural, Material.SOIL)[::50]]
    assert any(ok for ok, _ in verdicts), verdicts     # not vacuous: dry level ground still passes
    assert all(why != "water inside the disc" for _, why in verdicts)


def test_a_post_narrower_than_a_quarter_metre_cannot_fall_between_the_rays():
    """A 0.12 m post standing between the rays of a 0.25 m grid (1.1 m from the target, between rays at 1.0
    and 1.25 m) is missed at that spacing and found at the default 5 cm one."""
    from edge_landing.sim.fields import flat_field

    field = flat_field([(10.0, 1.125, 0.06, 0.06, 1.5)])          # north, east, half sizes, height
    assert check_target(field, 10.0, 0.0, TruthConfig(log="", clearance_m=2.0, sample_step_m=0.25)) == (True, "ok")
    ok, why = check_target(field, 10.0, 0.0, TruthConfig(log="", clearance_m=2.0))
    assert not ok and ("step" in why or "tilted" in why), why
    assert check_target(field, 10.0, -6.0, TruthConfig(log="", clearance_m=2.0)) == (True, "ok")   # open grass
