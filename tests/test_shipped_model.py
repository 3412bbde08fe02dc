"""The model shipped in the package: its contract, and accuracy floors on freshly rendered unseen scenes of both styles.

Floors are set well below what was measured when the model was shipped (see MEASURED below and
edge_landing/runtime/models/edgenet.json), so they catch a broken or placeholder model, not noise.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from edge_landing.evaluation.metrics import DepthAccumulator, HvoAccumulator
from edge_landing.evaluation.scene import Scene
from edge_landing.runtime.models import MODELS_DIR, default_model_path
from edge_landing.runtime.perception.contract import DepthConvention, Layout, Task
from edge_landing.runtime.perception.inference import OnnxModel

# Measured on this test's own scenes (suburban seed 101, urban seed 102, both unseen in training, 3 frames at
# 120×160): (horizontal precision, δ1 after one per-scene scale), with edge-sim's landing labels (2026-12-02; by the
# normals alone, when the model was shipped, the precisions were 0.920, 0.922, 0.925, 0.921).
MEASURED = {("edgenet.onnx", "suburban"): (0.910, 0.998), ("edgenet.int8.onnx", "suburban"): (0.912, 0.998),
            ("edgenet.onnx", "urban"): (0.909, 0.888), ("edgenet.int8.onnx", "urban"): (0.906, 0.862)}
# The random placeholder scored h_precision NaN (never says horizontal) and δ1 0.32 on the suburban scene; the
# suburban-only model of the first release scored 0.787 and 0.369 on the urban one (it would fail the urban floor).
FLOORS = {"suburban": (0.75, 0.70), "urban": (0.80, 0.65)}   # (precision, δ1)
SEEDS = {"suburban": 101, "urban": 102}
MIN_DEPTH_M, MAX_DEPTH_M = 1e-3, 1000.0


def _trained() -> bool:
    record = MODELS_DIR / "edgenet.json"
    return record.is_file() and json.loads(record.read_text()).get("weights") == "trained"


@pytest.fixture(scope="module")
def model():
    return OnnxModel.load(default_model_path(), threads=1)


def test_shipped_model_carries_the_contract(model):
    c = model.contract
    assert c.arch == "edgenet" and c.task is Task.DEPTH_HVO
    assert c.input.layout is Layout.NCHW and (c.input.height, c.input.width) == (240, 320)
    assert c.depth.convention is DepthConvention.METRIC and c.depth.stride == 2
    assert 0 < c.depth.min_depth < c.depth.max_depth
    assert c.hvo.output == "hvo_logits"
    assert "date" in c.source
    pred = model.predict(np.full((240, 320, 3), 90, np.uint8))
    assert pred.valid and pred.depth_m.shape == (120, 160) and pred.hvo_prob.shape == (120, 160, 3)
    assert np.allclose(pred.hvo_prob.sum(axis=2), 1.0, atol=1e-4)


def test_shipped_files_are_small():
    for name in ("edgenet.onnx", "edgenet.int8.onnx"):
        path = MODELS_DIR / name
        if path.exists():
            assert path.stat().st_size < 5e6, f"{name} is {path.stat().st_size / 1e6:.1f} MB"


@pytest.fixture(scope="module")
def unseen_scenes(tmp_path_factory):
    generate = pytest.importorskip("edge_landing.sim.generate")
    pytest.importorskip("embreex")
    root, scenes = tmp_path_factory.mktemp("shipped"), {}
    for style, seed in SEEDS.items():
        out = root / f"{style}{seed}"
        generate.generate(generate.SimConfig(out=out, frames=3, style=generate.Style.from_string(style), seed=seed,
                                             width=160, height=120, write_normals=False), progress=False)
        scenes[style] = Scene(out)
    return scenes


def score(model: OnnxModel, scene: Scene) -> dict:
    """Horizontal precision (global counts) and δ1 after one per-scene median scale (ARCHITECTURE.md §7)."""
    preds, gts, hvo = [], [], HvoAccumulator()
    for fid in scene.frame_ids:
        gt = scene.read_depth(fid)
        p = model.predict(scene.read_rgb(fid), out_hw=gt.shape)
        hvo.add(scene.read_hvo(fid), p.hvo_prob.argmax(axis=2))
        preds.append(p.depth_m)
        gts.append(gt)
    ratios = []
    for gt, pred in zip(gts, preds):
        ok = np.isfinite(gt) & np.isfinite(pred) & (gt > MIN_DEPTH_M) & (gt < MAX_DEPTH_M)
        ratios.append(np.median(gt[ok]) / np.median(pred[ok]))
    scale = float(np.median(ratios))
    depth = DepthAccumulator(MIN_DEPTH_M, MAX_DEPTH_M)
    for gt, pred in zip(gts, preds):
        depth.add(gt, pred * scale)
    return {"h_precision": hvo.result()["horizontal"]["precision"], "delta1_scene_scale": depth.result()["a1"]}


@pytest.mark.skipif(not _trained(), reason="the shipped edgenet is still the random placeholder")
@pytest.mark.parametrize("name,style", sorted(MEASURED))
def test_shipped_model_floor_on_unseen_scenes_of_both_styles(name, style, unseen_scenes):
    path = MODELS_DIR / name
    if not path.exists():
        pytest.skip(f"{name} is not shipped in this installation")
    got = score(OnnxModel.load(path, threads=1), unseen_scenes[style])
    floor_precision, floor_delta1 = FLOORS[style]
    assert got["h_precision"] >= floor_precision, got
    assert got["delta1_scene_scale"] >= floor_delta1, got


# -- the held-out style (issue 14) ------------------------------------------------------------------------
# edge-sim's rural/industrial style is never used for training or validation (export/datasets.py refuses it):
# our own zero-shot test. Measured when these floors were set (rural seed 103, 6 frames at 120×160, default
# camera): (H precision, H base rate, lift, δ1 after one scene scale), re-measured 2026-12-02 with the landing
# labels (trees, hedges, containers and water are "other"). The base rate is high (open fields), so the lift, not
# the precision, says whether the net sees anything: "horizontal everywhere" has lift 0.
HELD_OUT_SEED = 103
HELD_OUT_MEASURED = {"edgenet.onnx": (0.877, 0.796, 0.082, 0.636), "edgenet.int8.onnx": (0.874, 0.796, 0.078, 0.597)}
# (lift over the base rate, mIoU, δ1 after one scene scale): about half the measured lift (a net calling everything
# horizontal gets 0), under the measured mIoU 0.35 (0.40 with the geometric labels) and well under δ1 0.60-0.64.
# The goals (lift >= 0.20, δ1 >= 0.70) are not met by this model; see the README's accuracy table
# (all runs: docs/MEASUREMENTS.md, "The shipped model").
HELD_OUT_FLOORS = (0.04, 0.30, 0.40)


@pytest.fixture(scope="module")
def held_out_scene(tmp_path_factory):
    generate = pytest.importorskip("edge_landing.sim.generate")
    pytest.importorskip("embreex")
    out = tmp_path_factory.mktemp("held_out") / f"rural{HELD_OUT_SEED}"
    generate.generate(generate.SimConfig(out=out, frames=6, style=generate.Style.RURAL, seed=HELD_OUT_SEED,
                                         width=160, height=120, write_normals=False), progress=False)
    return Scene(out)


@pytest.mark.skipif(not _trained(), reason="the shipped edgenet is still the random placeholder")
@pytest.mark.parametrize("name", sorted(HELD_OUT_MEASURED))
def test_shipped_model_floor_on_the_held_out_rural_style(name, held_out_scene):
    path = MODELS_DIR / name
    if not path.exists():
        pytest.skip(f"{name} is not shipped in this installation")
    model = OnnxModel.load(path, threads=1)
    got = score(model, held_out_scene)
    hvo = HvoAccumulator()
    for fid in held_out_scene.frame_ids:
        hvo.add(held_out_scene.read_hvo(fid), model.predict(held_out_scene.read_rgb(fid), out_hw=(120, 160))
                .hvo_prob.argmax(axis=2))
    base = hvo.result()["baseline"]
    got.update(base_rate=base["horizontal_base_rate"], lift=base["horizontal_lift"], miou=base["miou"])
    print(f"\n{name} on held-out rural seed {HELD_OUT_SEED}: H precision {got['h_precision']:.3f} vs base rate "
          f"{got['base_rate']:.3f} (lift {got['lift']:+.3f}), mIoU {got['miou']:.3f}, "
          f"δ1 (scene scale) {got['delta1_scene_scale']:.3f}")
    assert got["lift"] >= HELD_OUT_FLOORS[0], got
    assert got["miou"] >= HELD_OUT_FLOORS[1], got
    assert got["delta1_scene_scale"] >= HELD_OUT_FLOORS[2], got
