import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from edge_landing.cli.eval_cli import main as eval_main
from edge_landing.evaluation.evaluate import EvalConfig, evaluate_scene
from edge_landing.evaluation.metrics import (
    DEPTH_KEYS,
    Averaging,
    depth_metrics,
    hvo_metrics,
    median_scaled_depth_metrics,
)
from edge_landing.evaluation.scene import Scene, SceneMeta, SceneWriter
from edge_landing.runtime.core.camera import Intrinsics
from edge_landing.runtime.perception.contract import Task
from edge_landing.runtime.perception.inference import OnnxModel
from tests.helpers import tiny_onnx_model

H, W = 16, 24


def known_rgb(rng, size):
    """One colour per frame, so that resizing the image and the model's outputs is exact."""
    return np.broadcast_to(rng.integers(0, 40, 3, dtype=np.uint8), (*size, 3)).copy()


def write_scene(path, frames=3, size=(H, W), depth=True, hvo=True, seed=0):
    """Ground truth = 2 × (1 + red) × noise, HVO = the brightest channel except where noise flips it."""
    rng = np.random.default_rng(seed)
    writer = SceneWriter(path, SceneMeta(intrinsics=Intrinsics.from_hfov(size[1], size[0])))
    for i in range(frames):
        rgb = rng.integers(0, 40, (*size, 3), dtype=np.uint8) if size == (H, W) else known_rgb(rng, size)
        gt = (2.0 * (1.0 + rgb[..., 0]) * rng.uniform(0.8, 1.2, size)).astype(np.float32)
        gt[0, :4] = np.nan
        labels = rgb.argmax(axis=2).astype(np.uint8)
        labels[rng.random(size) < 0.2] = rng.integers(0, 3)
        labels[-1, :] = 255
        writer.write(i, rgb, depth_m=gt if depth else None, hvo=labels if hvo else None)
    writer.close()
    if not depth:
        (path / "depth").rmdir()
    if not hvo:
        (path / "hvo").rmdir()
    return path


@pytest.fixture()
def model_path(tmp_path):
    return tiny_onnx_model(tmp_path / "tiny.onnx", H, W)


def independent_figures(scene_path, size=(H, W), depth_range=(1e-3, 80.0)):
    """What the tiny model must score, computed without the inference code: depth = 1 + red, HVO = argmax."""
    scene = Scene(scene_path)
    lo, hi = depth_range
    raw, star, cms = [], [], np.zeros((3, 3), np.int64)
    for fid in scene.frame_ids:
        rgb = scene.read_rgb(fid)
        pred = 1.0 + rgb[..., 0].astype(np.float64)
        gt = scene.read_depth(fid)
        raw.append(depth_metrics(gt, pred, lo, hi))
        star.append(median_scaled_depth_metrics(gt, pred, lo, hi))
        cms += np.asarray(hvo_metrics(scene.read_hvo(fid), rgb.argmax(axis=2))["confusion"])
    mean = lambda rows: {k: np.mean([r[k] for r in rows]) for k in DEPTH_KEYS}
    return mean(raw), mean(star), cms


def test_json_figures_match_an_independent_computation(tmp_path, model_path, capsys):
    scene = write_scene(tmp_path / "scene")
    out = tmp_path / "r.json"
    assert eval_main([str(model_path), str(scene), "--json", str(out), "--threads", "1"]) == 0
    printed = capsys.readouterr().out
    assert "δ1" in printed and "* tiny" in printed and "horizontal" in printed and "SSIM" in printed
    result = json.loads(out.read_text())
    m = result["models"][0]
    # No --min/--max-depth: the scored range is the model's contract range (edge.depth min/max).
    spec = OnnxModel.load(model_path).contract.depth
    assert (result["config"]["min_depth_m"], result["config"]["max_depth_m"]) == (spec.min_depth, spec.max_depth)
    assert "contract" in result["config"]["depth_range_source"]
    raw, star, cm = independent_figures(scene, depth_range=(spec.min_depth, spec.max_depth))
    for k in DEPTH_KEYS:
        assert m["depth"]["raw"][k] == pytest.approx(raw[k], rel=1e-5), k
        assert m["depth"]["median_scaled"][k] == pytest.approx(star[k], rel=1e-5, abs=1e-9), k
    assert m["hvo"]["confusion"] == cm.tolist()
    tp = cm[0, 0]
    assert m["hvo"]["horizontal"]["precision"] == pytest.approx(tp / cm[:, 0].sum())
    assert m["depth"]["median_scale"]["median"] == pytest.approx(2.0, rel=0.05)
    assert len(m["per_frame"]) == 3 and m["depth"]["calibrated"] is None


def test_predictions_are_resized_to_the_ground_truth(tmp_path, model_path):
    scene = write_scene(tmp_path / "scene", size=(2 * H, 2 * W))
    result = evaluate_scene([OnnxModel.load(model_path, threads=1)], Scene(scene), show_progress=False)
    m = result["models"][0]
    raw, _, cm = independent_figures(scene)
    assert m["depth"]["raw"]["abs_rel"] == pytest.approx(raw["abs_rel"], rel=1e-5)
    assert m["hvo"]["confusion"] == cm.tolist() and cm.sum() > 2 * H * W


def test_calibrated_rows_use_the_calibration_file(tmp_path, model_path, capsys):
    from edge_landing.calibration.cli import main as calibrate_main

    scene = write_scene(tmp_path / "scene")
    assert calibrate_main([str(scene), "--model", str(model_path)]) == 0
    scale = json.loads((scene / "calibration.json").read_text())["scale"]
    out = tmp_path / "r.json"
    assert eval_main([str(model_path), str(scene), "--calibration", str(scene / "calibration.json"),
                      "--json", str(out), "--min-depth", "1e-3", "--max-depth", "80", "--paper"]) == 0
    printed = capsys.readouterr().out
    assert "cal tiny" in printed and "paper * AdaBins-80" in printed and "paper SafeUAV-Net-Large" in printed
    result = json.loads(out.read_text())
    d = result["models"][0]["depth"]
    assert d["calibration"]["scale"] == pytest.approx(scale)
    sc = Scene(scene)
    expected = np.mean([depth_metrics(sc.read_depth(f), scale * (1.0 + sc.read_rgb(f)[..., 0]))["abs_rel"]
                        for f in sc.frame_ids])
    assert d["calibrated"]["abs_rel"] == pytest.approx(expected, rel=1e-5)
    assert result["paper"]["tables"] == [5, 6, 7]


def test_several_models_and_partial_scenes(tmp_path, capsys):
    depth_only = tiny_onnx_model(tmp_path / "d.onnx", H, W, task=Task.DEPTH)
    hvo_only = tiny_onnx_model(tmp_path / "h.onnx", H, W, task=Task.HVO)
    scene = write_scene(tmp_path / "full")
    out = tmp_path / "r.json"
    assert eval_main([str(depth_only), str(hvo_only), str(scene), "--json", str(out)]) == 0
    models = json.loads(out.read_text())["models"]
    assert models[0]["depth"] and models[0]["hvo"] is None
    assert models[1]["hvo"] and models[1]["depth"] is None
    capsys.readouterr()
    hvo_scene = write_scene(tmp_path / "hvo_only", depth=False)
    assert eval_main([str(depth_only), str(hvo_only), str(hvo_scene)]) == 0
    printed = capsys.readouterr().out
    assert "HVO" in printed and "δ1" not in printed and "nothing to be scored" in printed
    assert eval_main([str(depth_only), str(hvo_scene)]) == 2
    assert "nothing to evaluate" in capsys.readouterr().err


def test_figures_grid_is_written(tmp_path, model_path):
    scene = write_scene(tmp_path / "scene", frames=2)
    assert eval_main([str(model_path), str(scene), "--figures", str(tmp_path / "fig")]) == 0
    pngs = list((tmp_path / "fig").glob("*.png"))
    assert len(pngs) == 1
    img = cv2.imread(str(pngs[0]))
    # header + 2 rows; columns: RGB, GT depth, GT HVO, model depth, model HVO (240 px each)
    assert img.shape[1] == 5 * 240 and img.shape[0] == 22 + 2 * 160
    assert img[22:].std() > 0


def test_bad_input_is_one_line_and_nonzero(tmp_path, model_path, capsys):
    scene = write_scene(tmp_path / "scene", frames=1)
    cases = [
        ([str(scene)], "at least one model"),
        ([str(model_path), str(tmp_path / "nowhere")], "does not exist"),
        ([str(tmp_path / "missing.onnx"), str(scene)], "does not exist"),
        ([str(model_path), str(scene), "--min-depth", "5", "--max-depth", "1"], "min-depth"),
        ([str(model_path), str(scene), "--calibration", str(tmp_path / "nope.json")], "does not exist"),
    ]
    for argv, message in cases:
        assert eval_main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, err
    np.save(scene / "depth" / "000000.npy", np.ones((3, 3), np.float32))
    assert eval_main([str(model_path), str(scene)]) == 2
    assert "frame 000000" in capsys.readouterr().err
    (scene / "depth" / "000000.npy").write_text("not an array\n")   # numpy's own message speaks of pickles
    assert eval_main([str(model_path), str(scene)]) == 2
    assert "000000.npy is not a .npy file (no NumPy header)" in capsys.readouterr().err


def test_subprocess_exit_codes(tmp_path, model_path):
    scene = write_scene(tmp_path / "scene", frames=1)
    ok = subprocess.run([sys.executable, "-m", "edge_landing.cli.eval_cli", str(model_path), str(scene)],
                        capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert "AbsRel" in ok.stdout
    bad = subprocess.run([sys.executable, "-m", "edge_landing.cli.eval_cli", str(model_path), str(tmp_path)],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "no rgb/ folder" in bad.stderr and "Traceback" not in bad.stderr


def test_global_averaging_option(tmp_path, model_path):
    scene = write_scene(tmp_path / "scene")
    per = evaluate_scene([OnnxModel.load(model_path, threads=1)], Scene(scene), show_progress=False)
    glob = evaluate_scene([OnnxModel.load(model_path, threads=1)], Scene(scene),
                          EvalConfig(depth_averaging=Averaging.GLOBAL), show_progress=False)
    assert per["config"]["depth_averaging"] == "per-image" and glob["config"]["depth_averaging"] == "global"
    sc = Scene(scene)
    gts = np.concatenate([sc.read_depth(f).ravel() for f in sc.frame_ids])
    preds = np.concatenate([1.0 + sc.read_rgb(f)[..., 0].ravel().astype(np.float64) for f in sc.frame_ids])
    assert glob["models"][0]["depth"]["raw"]["rms"] == pytest.approx(depth_metrics(gts, preds)["rms"], rel=1e-5)
