"""edge-run's model flags: which file(s) run on this CPU, and their inference sessions (ARCHITECTURE.md §5, §9)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Optional, TextIO, Tuple, Union

from edge_landing.runtime.perception.precision import ModelChoice, ProbeConfig, pick_model
from edge_landing.runtime.perception.runtime_choice import pick_runtime
from edge_landing.runtime.pipeline import JointInference, PairInference

if TYPE_CHECKING:
    from edge_landing.cli.run import RunConfig


def add_model_arguments(parser: argparse.ArgumentParser) -> None:
    """edge-run's "model" group: the model file(s), precision and runtime, scale and threads."""
    m = parser.add_argument_group("model")
    m.add_argument("--model", help="joint depth+HVO ONNX model (default: the shipped edgenet)")
    m.add_argument("--precision", default="auto", help="auto (default): the faster on this CPU of the FP32 file and "
                   "its INT8 twin X.int8.onnx (if it passed edge-quantize's accuracy gate), probed once and cached in "
                   "~/.cache/edge-landing; fp32 or int8 to choose")
    m.add_argument("--int8", action="store_true", help="same as --precision int8")
    m.add_argument("--runtime", default="auto", help="auto (default): ONNX Runtime, or OpenVINO's CPU plugin on the "
                   "same file(s) when openvino is installed, agrees with ONNX Runtime and is faster here (probed once, "
                   "cached); onnxruntime or openvino to choose")
    m.add_argument("--depth-model", help="depth ONNX model (with --hvo-model)")
    m.add_argument("--hvo-model", help="HVO ONNX model (with --depth-model)")
    m.add_argument("--calibration", help="calibration.json from edge-calibrate (depth scale)")
    m.add_argument("--no-altitude-scale", action="store_true", help="do not estimate the scale from telemetry")
    m.add_argument("--threads", type=int, default=2, help="ONNX Runtime threads (the drone has 2 cores)")
    m.add_argument("--sequential", action="store_true", help="fuse each frame before the next inference "
                   "(default: fusion of frame N overlaps inference of frame N+1)")
    m.add_argument("--fusion-hz", type=float, default=0.0, help="fuse at most this many frames per second (>= 10; "
                   "the others are inferred but give no target), leaving the cores to the model when the camera "
                   "is faster than the whole pipeline (0 = fuse every frame, the default)")


def choose_files(cfg: RunConfig) -> Tuple[ModelChoice, ...]:
    """The file(s) to run: for each FP32 model, it or its INT8 twin (``--precision``, default the faster here)."""
    from edge_landing.runtime.models import default_model_path

    probe = ProbeConfig(threads=cfg.threads)
    given = (cfg.depth_model, cfg.hvo_model) if cfg.depth_model and cfg.hvo_model else (cfg.model,) if cfg.model else ()
    paths = [Path(p) for p in given if p] or [default_model_path()]
    return tuple(pick_runtime(pick_model(p, cfg.precision, probe), p, cfg.precision, cfg.runtime, probe) for p in paths)


def load_inference(cfg: RunConfig, out: Optional[TextIO] = None) -> Union[JointInference, PairInference]:
    from edge_landing.runtime.perception.inference import OnnxModel, SessionConfig

    choices = choose_files(cfg)
    for choice in choices:
        print(f"edge-run: {choice.line()}", file=out or sys.stdout, flush=True)
    models = [OnnxModel.load(c.path, config=SessionConfig(threads=cfg.threads, runtime=c.runtime)) for c in choices]
    return PairInference(models[0], models[1]) if len(models) == 2 else JointInference(models[0])
