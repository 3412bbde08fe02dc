"""The models of the speed report and how to get them: exported FP32, quantized INT8, PyTorch eager.

Every model is exported from the zoo at the paper's input size into a cache folder (random weights when no
checkpoint is given: speed does not depend on the values) and quantized with ``export.quantize`` on a
calibration scene (a given one, or a few synthetic frames written next to the cache). Example::

    prepared = prepare(CATALOG["safeuav-small"], PrepareConfig(cache_dir=Path("bench_cache")))
    print(prepared.fp32_path, prepared.int8_path, prepared.params)
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple

import numpy as np

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.perception.contract import ModelContract, Task
from edge_landing.runtime.perception.inference import read_contract

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BenchModel:
    """One row of the report: a zoo architecture with its head and options, and the paper's V100 figure."""

    name: str
    arch: str
    task: Task
    options: Tuple[Tuple[str, object], ...] = ()
    paper_v100_images_per_s: Optional[float] = None
    paper_rows: str = ""
    paper_size_mb: Optional[float] = None      # Table 1's "model size": the authors' files, not ONNX
    input_hw: Optional[Tuple[int, int]] = None  # default: the architecture's own input size
    peer_note: str = ""                        # printed under the table (e.g. what a peer row is)


_DA_NOTE = ("speed only, random weights: the Depth Anything V2 Small architecture from its published configuration "
            "(transformers' DepthAnythingForDepthEstimation), not the trained model")
CATALOG = {m.name: m for m in (
    BenchModel("adabins-80", "adabins", Task.DEPTH, (("bins", 80),), 9.623, "AdaBins-80", 917),
    BenchModel("adabins-256", "adabins", Task.DEPTH, (("bins", 256),), 9.583, "AdaBins-256", 918),
    BenchModel("densedepth", "densedepth", Task.DEPTH, (), 28.835, "DD-UAV, DD-UAV-NYU", 337),
    BenchModel("safeuav-large", "safeuav-large", Task.HVO, (), 27.853, "SafeUAV-Net-Large", 650),
    BenchModel("safeuav-small", "safeuav-small", Task.HVO, (), 101.366, "SafeUAV-Net-Small", 24),
    BenchModel("edgenet", "edgenet", Task.DEPTH_HVO, (), None, "this project's joint depth+HVO net"),
    # What a user would pick for depth today: Depth Anything V2 Small, at its usual input and at ours.
    BenchModel("depth-anything-v2-small", "depth-anything-v2-small", Task.DEPTH, (), None, "",
               peer_note=_DA_NOTE),
    BenchModel("depth-anything-v2-small-240", "depth-anything-v2-small", Task.DEPTH, (), None, "",
               input_hw=(240, 320), peer_note=_DA_NOTE + "; at 240x320 it sees 17x22 patches (238x308 px)"),
)}
# The peers are left out of the default set (they need transformers, and DA at 518x518 takes ~0.5 s a frame).
PEERS = ("depth-anything-v2-small", "depth-anything-v2-small-240")
# AdaBins (78 M parameters, ~0.3 GB of ONNX per variant, seconds per image on 2 cores) is left out of the
# default set to keep a default run reasonable; ask for it with --models adabins-80,adabins-256.
DEFAULT_MODELS = ("densedepth", "safeuav-large", "safeuav-small", "edgenet")
QUICK_MODELS = ("safeuav-small",)


def lookup(names) -> Tuple[BenchModel, ...]:
    out = []
    for name in names:
        if name not in CATALOG:
            raise InputError(f"unknown model '{name}' for edge-bench; expected one of: {', '.join(CATALOG)}")
        out.append(CATALOG[name])
    return tuple(out)


@dataclass(frozen=True)
class PrepareConfig:
    cache_dir: Path
    height: Optional[int] = None          # default: the paper's input size of the architecture
    width: Optional[int] = None
    calib_scene: Optional[Path] = None    # default: synthetic frames written into the cache
    # few frames: ONNX Runtime's calibrator keeps every activation of every frame in memory (gigabytes for
    # DenseDepth at 480x640), and speed does not depend on how well the ranges fit
    calib_frames: int = 4
    eval_frames: int = 2
    rebuild: bool = False
    progress: bool = True
    checkpoints: Tuple[Tuple[str, Path], ...] = ()   # (model name, checkpoint): trained weights instead of random


@dataclass(frozen=True)
class Prepared:
    model: BenchModel
    fp32_path: Path
    int8_path: Path
    contract: ModelContract
    params: int
    int8_agreement: Optional[float]
    module: object        # the torch.nn.Module (random weights) for the PyTorch eager column


def input_hw(model: BenchModel, config: PrepareConfig) -> Tuple[int, int]:
    from edge_landing.export.zoo import get_arch

    spec = get_arch(model.arch)
    own = model.input_hw or spec.input_hw
    return (config.height or own[0], config.width or own[1])


def synthetic_calibration_scene(path: Path, height: int, width: int, frames: int, seed: int = 0) -> Path:
    """Smooth random colour fields at the model's size: enough to set activation ranges for a speed test
    (random-weight models have no accuracy to keep). Pass a real scene (edge-sim) for real models."""
    import cv2

    from edge_landing.evaluation.scene import Scene, SceneMeta, SceneWriter
    from edge_landing.runtime.core.camera import Intrinsics

    if path.is_dir() and (path / "scene.json").exists() and len(Scene(path)) >= frames:
        return path
    rng = np.random.default_rng(seed)
    writer = SceneWriter(path, SceneMeta(intrinsics=Intrinsics.from_hfov(width, height),
                                         generator={"name": "edge-bench synthetic calibration", "seed": seed}))
    for i in range(frames):
        coarse = rng.uniform(0, 255, (max(height // 16, 2), max(width // 16, 2), 3)).astype(np.float32)
        rgb: np.ndarray = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
        rgb += rng.normal(0, 8, rgb.shape).astype(np.float32)   # some texture on top of the blobs
        writer.write(i, np.clip(rgb, 0, 255).astype(np.uint8))
    writer.close()
    return path


def prepare(model: BenchModel, config: PrepareConfig) -> Prepared:
    """Export (if not cached), quantize (if not cached) and read back the contract and agreement."""
    from edge_landing.export.onnx_export import ExportSettings, export_onnx
    from edge_landing.export.quantize import QuantizeConfig, quantize
    from edge_landing.export.zoo import get_arch

    spec = get_arch(model.arch)
    h, w = input_hw(model, config)
    checkpoint = dict(config.checkpoints).get(model.name)
    config.cache_dir.mkdir(parents=True, exist_ok=True)
    stem = f"{model.name}_{h}x{w}" + (f"_{Path(checkpoint).stem}" if checkpoint else "")
    fp32, int8 = config.cache_dir / f"{stem}.onnx", config.cache_dir / f"{stem}.int8.onnx"
    if config.rebuild or not fp32.exists():
        export_onnx(spec, model.task, fp32, h, w, checkpoint=checkpoint, options=dict(model.options),
                    settings=ExportSettings(progress=config.progress))
        if int8.exists():
            int8.unlink()   # quantized from the old export
    if config.rebuild or not int8.exists():
        scene = config.calib_scene or synthetic_calibration_scene(
            config.cache_dir / f"calib_{h}x{w}", h, w, config.calib_frames + config.eval_frames)
        # force: a speed report keeps every model; the agreement is measured and reported either way.
        quantize(fp32, int8, QuantizeConfig(calib_scene=scene, calib_frames=config.calib_frames,
                                            eval_frames=config.eval_frames, force=True, progress=config.progress,
                                            speed_gate=False))   # edge-bench times them itself
    contract = read_contract(fp32)
    q = read_contract(int8).quantization or {}
    comparison = q.get("comparison", {})
    head = comparison.get("hvo") or comparison.get("depth") or {}
    agreement = head.get("agreement")
    module = spec.build(model.task, **dict(model.options)).eval()
    if checkpoint:
        spec.load_checkpoint(module, Path(checkpoint))
    params = sum(p.numel() for p in module.parameters())
    return Prepared(model, fp32, int8, contract, int(params), agreement, module)
