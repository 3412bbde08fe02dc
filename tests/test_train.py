"""edge-train on tiny scenes written in the test: losses, a few real optimisation steps, checkpoint/resume, export."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from edge_landing.evaluation.scene import SceneMeta, SceneWriter  # noqa: E402
from edge_landing.export.augment import AugmentConfig, Augmenter  # noqa: E402
from edge_landing.export.losses import DepthLossSpace, depth_loss, hvo_loss  # noqa: E402
from edge_landing.export.train import TrainConfig, _Setup, compute_losses, train  # noqa: E402
from edge_landing.export.train_cli import main as train_main  # noqa: E402
from edge_landing.export.zoo import get_arch  # noqa: E402
from edge_landing.runtime.core.camera import Intrinsics  # noqa: E402
from edge_landing.runtime.perception.contract import DepthConvention, Task  # noqa: E402
from edge_landing.runtime.perception.inference import OnnxModel  # noqa: E402

H, W = 32, 48


def write_tiny_scene(path: Path, frames: int = 4, seed: int = 0) -> Path:
    """Sky on top (NaN depth, label 255), ground below (depth shrinking towards the bottom, horizontal, green)
    and a grey wall block (vertical); colours tie the labels to the image so the net can learn them."""
    rng = np.random.default_rng(seed)
    writer = SceneWriter(path, SceneMeta(Intrinsics.from_hfov(W, H), generator={"name": "test", "seed": seed,
                                                                                "style": "tiny"}))
    rows = np.arange(H, dtype=np.float32)[:, None].repeat(W, axis=1)
    for i in range(frames):
        horizon = int(rng.integers(6, 10))
        rgb = np.zeros((H, W, 3), np.uint8)
        depth = (400.0 / np.maximum(rows - horizon + 1.0, 1.0)).astype(np.float32)
        hvo = np.zeros((H, W), np.uint8)
        rgb[:] = (60, 140, 60)
        x0 = int(rng.integers(4, W - 20))
        rgb[horizon:H - 6, x0:x0 + 14] = (128, 128, 128)
        hvo[horizon:H - 6, x0:x0 + 14] = 1
        depth[horizon:H - 6, x0:x0 + 14] = depth[H - 7, 0]
        rgb[:horizon] = (140, 180, 230)
        hvo[:horizon] = 255
        depth[:horizon] = np.nan
        writer.write(i, rgb, depth, hvo)
    writer.close()
    return path


@pytest.fixture(scope="module")
def tiny_scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("scenes")
    return write_tiny_scene(root / "train", 4, seed=1), write_tiny_scene(root / "val", 2, seed=2)


def test_depth_loss_is_zero_for_perfect_prediction_and_ignores_invalid():
    space = DepthLossSpace(DepthConvention.METRIC, 1.0, 1000.0)
    gt = torch.full((1, 1, 16, 16), 50.0)
    gt[..., :4, :] = float("nan")
    target, valid = space.target_to_loss(gt), space.valid(gt)
    pred = torch.where(valid, target, torch.full_like(target, 7.0))   # garbage where invalid
    terms = depth_loss(pred, target, valid)
    assert float(terms["total"]) == pytest.approx(0.0, abs=1e-6)
    worse = depth_loss(pred + 0.1, target, valid)
    assert float(worse["l1"]) == pytest.approx(0.1, rel=1e-4)
    # a constant offset in log space (a global scale error) costs nothing in the gradient term
    assert float(worse["grad"]) == pytest.approx(0.0, abs=1e-6)


def test_hvo_loss_ignores_255_and_all_ignored_is_zero():
    logits = torch.zeros(1, 3, 4, 4, requires_grad=True)
    labels = torch.full((1, 4, 4), 255, dtype=torch.long)
    assert float(hvo_loss(logits, labels).detach()) == 0.0
    labels[0, 0, 0] = 1
    assert float(hvo_loss(logits, labels).detach()) == pytest.approx(math.log(3), rel=1e-5)


def test_flip_keeps_labels_and_depth_aligned_with_the_image():
    aug = Augmenter(AugmentConfig(flip_p=1.0, brightness=0, contrast=0, saturation=0, channel_gain=0, blur_p=0,
                                  noise_p=0))
    rgb = torch.rand(2, 3, 4, 5)
    depth = torch.arange(40, dtype=torch.float32).view(2, 4, 5)
    hvo = (torch.arange(40).view(2, 4, 5) % 3)
    r, d, h = aug(rgb, depth, hvo)
    assert torch.equal(r, rgb.flip(-1)) and torch.equal(d, depth.flip(-1)) and torch.equal(h, hvo.flip(-1))
    r2, _, _ = Augmenter(AugmentConfig(), seed=3)(rgb, depth, hvo)
    assert r2.shape == rgb.shape and float(r2.min()) >= 0.0 and float(r2.max()) <= 1.0


def test_loss_decreases_on_one_batch(tiny_scenes):
    from edge_landing.export.datasets import load_scenes

    torch.manual_seed(0)
    torch.set_num_threads(1)
    spec = get_arch("edgenet")
    contract = spec.contract(Task.DEPTH_HVO, H, W, channels=8)
    setup = _Setup(Task.DEPTH_HVO, contract, spec.output_names(Task.DEPTH_HVO),
                   DepthLossSpace.from_spec(contract.depth), 1.0)
    model = spec.build(Task.DEPTH_HVO, channels=8)
    data = load_scenes([tiny_scenes[0]], H, W, True, True, progress=False)
    b = data.batch(range(len(data)))
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(8):
        terms = compute_losses(model, b.rgb, b.depth_m, b.hvo, setup)
        assert all(torch.isfinite(v) for v in terms.values())
        opt.zero_grad()
        terms["total"].backward()
        opt.step()
        losses.append(float(terms["total"].detach()))
    assert losses[-1] < 0.8 * losses[0], losses


def test_train_checkpoint_resume_and_export(tiny_scenes, tmp_path):
    train_dir, val_dir = tiny_scenes
    out = tmp_path / "run"
    base = dict(arch="edgenet", train_scenes=(str(train_dir),), val_scenes=(str(val_dir),), out_dir=str(out),
                batch=2, lr=2e-3, height=H, width=W, export_height=H, export_width=W, options=(("channels", 8),),
                progress=False)
    first = train(TrainConfig(epochs=1, export=False, **base))
    assert first.last_checkpoint.is_file() and first.best_checkpoint.is_file()
    assert math.isfinite(first.history[0]["train"]["total"])
    assert {"delta1_median_scaled", "h_precision"} <= set(first.history[0]["val"])
    resumed = train(TrainConfig(epochs=2, resume=str(first.last_checkpoint), export=True, **base))
    assert [r["epoch"] for r in resumed.history] == [1, 2]
    model = OnnxModel.load(resumed.onnx_path, threads=1)
    c = model.contract
    assert c.arch == "edgenet" and c.task is Task.DEPTH_HVO and (c.input.height, c.input.width) == (H, W)
    assert c.depth.convention is DepthConvention.METRIC and c.depth.stride == 2
    training = c.source["training"]
    assert training["epochs"] == 2 and training["train_scenes"][0]["generator"]["seed"] == 1
    assert training["resumed_from"] == str(first.last_checkpoint) and training["git_commit"]
    pred = model.predict(np.full((H, W, 3), 100, np.uint8))
    assert pred.valid and pred.depth_m.shape == (H // 2, W // 2) and pred.hvo_prob.shape == (H // 2, W // 2, 3)
    assert json.loads((out / "record.json").read_text())["epochs"] == 2


def test_cli_trains_safeuav_small_hvo_and_reports_bad_input(tiny_scenes, tmp_path, capsys):
    train_dir, _ = tiny_scenes
    rc = train_main(["--arch", "safeuav-small", "--task", "hvo", "--train", str(train_dir), "--epochs", "1",
                     "--batch", "2", "--height", "32", "--width", "48", "--max-steps", "1", "--out",
                     str(tmp_path / "s"), "--no-export", "--no-progress"])
    assert rc == 0 and (tmp_path / "s" / "best.pth").is_file()
    rc = train_main(["--arch", "edgenet", "--train", str(tmp_path / "missing"), "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert rc != 0 and "does not exist" in err and len(err.strip().splitlines()) == 1


def test_widening_keeps_what_the_narrow_edgenet_computes():
    from edge_landing.export.zoo.edgenet import widen_state_dict
    spec = get_arch("edgenet")
    torch.manual_seed(0)
    narrow = spec.build(Task.DEPTH_HVO, channels=8)
    narrow.train()
    x = torch.randn(2, 3, H, W)
    for _ in range(3):      # non-trivial BatchNorm running statistics
        narrow(x)
    narrow.eval()
    wide = spec.build(Task.DEPTH_HVO, channels=12)
    wide.load_state_dict(widen_state_dict(narrow.state_dict(), wide))
    wide.eval()
    with torch.no_grad():
        (d_n, h_n), (d_w, h_w) = narrow(x), wide(x)
    assert torch.allclose(d_n, d_w, rtol=1e-4) and torch.allclose(h_n, h_w, atol=1e-4)
    # New channels are live (random incoming weights), so they can learn; old ones ignore them for now.
    assert float(wide.stem[0][0].weight[8:].detach().abs().sum()) > 0
    assert float(wide.enc2[0][0].weight[:12, 8:].detach().abs().sum()) == 0


def test_init_widens_a_narrow_checkpoint_and_pools_validation_scenes(tiny_scenes, tmp_path):
    train_dir, val_dir = tiny_scenes
    base = dict(arch="edgenet", train_scenes=(str(train_dir),), batch=2, lr=1e-3, height=H, width=W, epochs=1,
                max_steps_per_epoch=1, export=False, progress=False)
    narrow = train(TrainConfig(out_dir=str(tmp_path / "n"), options=(("channels", 8),), **base))
    wide = train(TrainConfig(out_dir=str(tmp_path / "w"), options=(("channels", 12),), init=str(narrow.best_checkpoint),
                             val_scenes=(str(val_dir), str(train_dir)), **base))
    record = wide.record
    assert [s["path"] for s in record["val_scenes"]] == [str(val_dir), str(train_dir)]
    assert math.isfinite(wide.history[0]["val"]["total"])
    state = torch.load(wide.best_checkpoint, weights_only=True)["model"]
    assert tuple(state["stem.0.0.weight"].shape) == (12, 3, 3, 3)
