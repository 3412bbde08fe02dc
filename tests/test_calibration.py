import json
import logging
import math
import subprocess
import sys

import numpy as np
import pytest

from edge_landing.calibration.cli import main as calibrate_main
from edge_landing.calibration.scene_scale import calibrate_scene
from edge_landing.evaluation.scene import Scene, SceneMeta, SceneWriter
from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.perception.calibration_file import (
    load_calibration,
    read_calibration,
)
from edge_landing.runtime.perception.contract import Task
from edge_landing.runtime.perception.inference import OnnxModel
from edge_landing.runtime.perception.scale import (
    AltitudeScaleConfig,
    AltitudeScaleEstimator,
    frame_scale,
    ground_plane_depth,
)
from tests.helpers import tiny_onnx_model

H, W = 16, 24


def write_scaled_scene(path, scale=2.5, frames=6, noise=0.02, seed=0, depth=True, size=(H, W)):
    """A scene whose ground truth is ``scale`` × the tiny model's prediction (1 + red), times noise."""
    rng = np.random.default_rng(seed)
    writer = SceneWriter(path, SceneMeta(intrinsics=Intrinsics.from_hfov(size[1], size[0])))
    for i in range(frames):
        rgb = rng.integers(0, 60, (*size, 3), dtype=np.uint8)
        pred = 1.0 + rgb[..., 0].astype(np.float64)
        gt = (scale * pred * (1 + noise * rng.standard_normal(size))).astype(np.float32)
        gt[0, :3] = np.nan                                # some invalid (sky) pixels
        writer.write(i, rgb, depth_m=gt if depth else None)
    writer.close()
    return path


@pytest.fixture()
def model_path(tmp_path):
    return tiny_onnx_model(tmp_path / "tiny.onnx", H, W)


def test_calibration_recovers_a_known_scale(tmp_path, model_path):
    scene = Scene(write_scaled_scene(tmp_path / "scene", scale=2.5))
    model = OnnxModel.load(model_path, threads=1)
    cal = calibrate_scene(scene, model, show_progress=False)
    assert cal.scale == pytest.approx(2.5, rel=0.01)
    assert cal.frames_used == cal.frames_total == 6 and cal.reliable
    assert cal.min_ratio <= cal.scale <= cal.max_ratio and cal.mad < 0.02
    assert cal.model_sha256 == model.sha256


def test_frames_without_ground_truth_are_counted_not_said_one_by_one(tmp_path, model_path, caplog):
    path = write_scaled_scene(tmp_path / "scene", scale=2.5, frames=10)
    for i in range(1, 9):   # eight frames whose depth is all sky
        np.save(path / "depth" / f"{i:06d}.npy", np.full((H, W), np.nan, np.float32))
    with caplog.at_level(logging.WARNING):
        cal = calibrate_scene(Scene(path), OnnxModel.load(model_path, threads=1), show_progress=False)
    assert cal.frames_used == 2 and cal.scale == pytest.approx(2.5, rel=0.02)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 4, said          # the first three, then one count
    assert said[-1].startswith("8 frame(s) skipped: no valid ground-truth pixel") and "last 000008" in said[-1]


def test_cli_writes_scene_calibration_json_and_it_loads_back(tmp_path, model_path, capsys):
    scene = write_scaled_scene(tmp_path / "scene", scale=0.4)
    assert calibrate_main([str(scene), "--model", str(model_path), "--threads", "1"]) == 0
    data = json.loads((scene / "calibration.json").read_text())
    assert data["scale"] == pytest.approx(0.4, rel=0.01)
    for key in ("mad", "min_ratio", "max_ratio", "frames_used", "model_sha256", "model_path", "scene_path",
                "created_utc", "ratios"):
        assert key in data
    sha = OnnxModel.load(model_path, threads=1).sha256
    assert load_calibration(scene / "calibration.json", model_sha256=sha) == pytest.approx(data["scale"])
    assert f"scale {data['scale']:.4f}" in capsys.readouterr().out


def test_wrong_model_sha_warns_or_errors(tmp_path, model_path, caplog):
    scene = write_scaled_scene(tmp_path / "scene", frames=2)
    calibrate_main([str(scene), "--model", str(model_path), "--out", str(tmp_path / "c.json")])
    with caplog.at_level("WARNING"):
        assert load_calibration(tmp_path / "c.json", model_sha256="0" * 64) == pytest.approx(2.5, rel=0.02)
    assert "not for this model" in caplog.text
    with pytest.raises(InputError, match="re-run edge-calibrate"):
        load_calibration(tmp_path / "c.json", model_sha256="0" * 64, strict=True)


def test_spread_out_scene_is_flagged_unreliable(tmp_path, model_path, capsys):
    scene = tmp_path / "scene"
    writer = SceneWriter(scene, SceneMeta(intrinsics=Intrinsics.from_hfov(W, H)))
    for i, s in enumerate((1.0, 2.0, 3.0, 4.0)):
        rgb = np.full((H, W, 3), 9, np.uint8)
        writer.write(i, rgb, depth_m=np.full((H, W), 10.0 * s, np.float32))
    writer.close()
    assert calibrate_main([str(scene), "--model", str(model_path)]) == 0
    assert "frames disagree" in capsys.readouterr().out
    assert read_calibration(scene / "calibration.json").reliable is False


def test_scene_without_depth_is_refused_with_one_line(tmp_path, model_path, capsys):
    scene = write_scaled_scene(tmp_path / "scene", frames=1, depth=False)
    (scene / "depth").rmdir()
    assert calibrate_main([str(scene), "--model", str(model_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no depth/ folder" in err and "edge-calibrate" in err


def test_empty_and_malformed_inputs_give_clear_errors(tmp_path, model_path, capsys):
    (tmp_path / "empty" / "rgb").mkdir(parents=True)
    assert calibrate_main([str(tmp_path / "empty"), "--model", str(model_path)]) == 2
    assert "is empty" in capsys.readouterr().err
    scene = write_scaled_scene(tmp_path / "scene", frames=2)
    (scene / "depth" / "000001.npy").write_bytes(b"not numpy")
    assert calibrate_main([str(scene), "--model", str(model_path)]) == 2
    assert "000001" in capsys.readouterr().err
    all_nan = write_scaled_scene(tmp_path / "nan", frames=1)
    np.save(all_nan / "depth" / "000000.npy", np.full((H, W), np.nan, np.float32))
    assert calibrate_main([str(all_nan), "--model", str(model_path)]) == 2
    assert "nothing to calibrate" in capsys.readouterr().err
    hvo_only = tiny_onnx_model(tmp_path / "hvo.onnx", H, W, task=Task.HVO)
    assert calibrate_main([str(scene), "--model", str(hvo_only)]) == 2
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(InputError, match="not valid JSON"):
        load_calibration(tmp_path / "bad.json")


def test_cli_subprocess_exit_codes(tmp_path, model_path):
    scene = write_scaled_scene(tmp_path / "scene", frames=2)
    ok = subprocess.run([sys.executable, "-m", "edge_landing.calibration.cli", str(scene), "--model", str(model_path)],
                        capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert (scene / "calibration.json").exists()
    bad = subprocess.run([sys.executable, "-m", "edge_landing.calibration.cli", str(tmp_path / "nowhere"), "--model",
                          str(model_path)], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "does not exist" in bad.stderr and "Traceback" not in bad.stderr


# -- in-flight scale from altitude --------------------------------------------------------------------------
def plane_frame(agl_m, attitude, true_scale, noise=0.03, seed=0, size=(48, 64)):
    """Predicted depth of flat ground = true depth / true_scale (with noise), HVO all horizontal."""
    intr = Intrinsics.from_hfov(size[1], size[0])
    gt = ground_plane_depth(intr, Mount(), attitude, agl_m)
    rng = np.random.default_rng(seed)
    pred = gt / true_scale * (1 + noise * rng.standard_normal(gt.shape))
    hvo = np.zeros((*size, 3), np.float32)
    hvo[..., 0] = 1.0
    return intr, gt, pred, hvo


def test_ground_plane_depth_puts_points_on_the_plane():
    from edge_landing.runtime.core.camera import ned_from_camera

    att = Attitude(0.1, -0.05, 1.2)
    intr = Intrinsics.from_hfov(64, 48)
    depth = ground_plane_depth(intr, Mount(), att, 40.0)
    pts = intr.backproject(depth.astype(np.float32)).reshape(-1, 3) @ ned_from_camera(Mount(), att).T
    assert np.nanmax(np.abs(pts[:, 2] - 40.0)) < 1e-3
    # the optical axis 45° below the horizon, level flight: z = h / sin 45°
    centre = ground_plane_depth(Intrinsics(65, 49, 32.0, 32.0, 32.5, 24.5), Mount(), Attitude(), 30.0)
    assert centre[24, 32] == pytest.approx(30.0 * math.sqrt(2), rel=1e-6)


@pytest.mark.parametrize("attitude", [Attitude(), Attitude(0.15, -0.1, 2.0)])
def test_altitude_scale_recovers_true_scale_on_a_plane(attitude):
    intr, _, pred, hvo = plane_frame(55.0, attitude, true_scale=3.2)
    est = AltitudeScaleEstimator().update(pred, hvo, intr, Mount(), attitude, 55.0)
    assert est.valid and est.scale == pytest.approx(3.2, rel=0.05)
    assert 0.5 < est.quality <= 1 and est.fraction > 0.9
    # without an HVO head the depth's own slope picks the ground
    est = AltitudeScaleEstimator().update(pred, None, intr, Mount(), attitude, 55.0)
    assert est.valid and est.scale == pytest.approx(3.2, rel=0.05)


def test_only_horizontal_votes_count():
    intr, gt, pred, hvo = plane_frame(40.0, Attitude(), true_scale=2.0, noise=0.0)
    hvo[:24] = (0.0, 1.0, 0.0)          # top half voted vertical ...
    pred[:24] *= 0.25                   # ... and its depth is a wall much nearer: must be ignored
    fs = frame_scale(pred, hvo, intr, Mount(), Attitude(), 40.0)
    assert fs.ok and fs.scale == pytest.approx(2.0, rel=1e-4) and fs.fraction == pytest.approx(0.5, abs=0.02)


def test_smoothing_gating_and_reset():
    cfg = AltitudeScaleConfig(alpha=0.5, reset_after=3)
    est = AltitudeScaleEstimator(cfg)
    att = Attitude()
    for seed in range(5):
        intr, _, pred, hvo = plane_frame(50.0, att, 2.0, seed=seed)
        e = est.update(pred, hvo, intr, Mount(), att, 50.0)
    assert e.valid and e.scale == pytest.approx(2.0, rel=0.02)
    intr, _, pred, hvo = plane_frame(50.0, att, 4.0)
    e = est.update(pred, hvo, intr, Mount(), att, 50.0)          # one outlier frame: gated out
    assert e.valid and e.scale == pytest.approx(2.0, rel=0.02) and "disagrees" in e.reason
    for _ in range(2):
        e = est.update(pred, hvo, intr, Mount(), att, 50.0)
    assert e.scale == pytest.approx(4.0, rel=0.02) and "reset" in e.reason   # the terrain really changed


def test_bad_frames_are_marked_invalid_not_raised():
    intr, _, pred, hvo = plane_frame(50.0, Attitude(), 2.0)
    est = AltitudeScaleEstimator(AltitudeScaleConfig(max_hold_frames=1))
    for agl in (None, float("nan"), 0.2):
        e = est.update(pred, hvo, intr, Mount(), Attitude(), agl)
        assert not e.valid and "height above ground" in e.reason
    looking_up = Mount(pitch_rad=math.radians(60))
    e = est.update(pred, hvo, intr, looking_up, Attitude(), 50.0)
    assert not e.valid and "too little ground" in e.reason
    e = est.update(pred[:10], hvo, intr, Mount(), Attitude(), 50.0)
    assert not e.valid and "shape" in e.reason
    e = est.update(pred, hvo, intr, Mount(), Attitude(), 50.0)
    assert e.valid
    for _ in range(2):
        e = est.update(np.full_like(pred, np.nan), hvo, intr, Mount(), Attitude(), 50.0)
    assert not e.valid and "stale" in e.reason


# -- the same on generator scenes (sim ray casts real geometry: houses, trees, gentle terrain) -----------------
@pytest.fixture(scope="module")
def sim_scenes(tmp_path_factory):
    sim = pytest.importorskip("edge_landing.sim")
    pytest.importorskip("embreex")
    root = tmp_path_factory.mktemp("sim")
    common = dict(style=sim.Style.SUBURBAN, seed=2, width=96, height=72, write_normals=False)
    views = sim.generate(sim.SimConfig(out=root / "views", frames=6, **common), progress=False)
    flight = sim.generate(sim.SimConfig(out=root / "flight", frames=16, flight=True, **common), progress=False)
    return Scene(views), Scene(flight)


def _sim_frames(scene, true_scale, noise, seed=0):
    """(predicted depth = truth / true_scale × noise, one-hot HVO from the truth, attitude, agl) per frame."""
    rng = np.random.default_rng(seed)
    poses = scene.poses()
    for fid in scene.frame_ids:
        gt, labels, pose = scene.read_depth(fid), scene.read_hvo(fid), poses[fid]
        prob = np.stack([(labels == k) for k in range(3)], axis=-1).astype(np.float32)
        pred = gt / true_scale * rng.uniform(1 - noise, 1 + noise, gt.shape)
        yield pred, prob, Attitude(pose.roll_rad, pose.pitch_rad, pose.yaw_rad), pose.agl_m


def test_altitude_scale_on_generator_views(sim_scenes):
    # Independent views, one frame each: a view whose rangefinder happens to read a roof is off by the
    # roof's height / agl, so allow one such view in six (the running estimator gates those out).
    views, _ = sim_scenes
    errors = [abs(frame_scale(pred, prob, views.meta.intrinsics, views.meta.mount, att, agl).scale / 3.0 - 1)
              for pred, prob, att, agl in _sim_frames(views, 3.0, noise=0.1)]
    assert sum(e < 0.05 for e in errors) >= len(errors) - 1, errors
    assert np.median(errors) < 0.02, errors


def test_altitude_scale_through_a_generator_flight(sim_scenes):
    # the flight tilts the vehicle while manoeuvring and passes over houses (the rangefinder jumps)
    _, flight = sim_scenes
    assert any(abs(p.pitch_rad) > math.radians(2) for p in flight.poses().values())
    est = AltitudeScaleEstimator()
    for pred, prob, att, agl in _sim_frames(flight, 0.5, noise=0.1):
        e = est.update(pred, prob, flight.meta.intrinsics, flight.meta.mount, att, agl)
        assert e.valid and e.scale == pytest.approx(0.5, rel=0.05), e
