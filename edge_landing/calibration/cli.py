"""``edge-calibrate SCENE [--model MODEL.onnx] [--out FILE]``: the scene's median depth scale for a model.

The model defaults to the shipped one and the result goes to ``SCENE/calibration.json``.
"""
from __future__ import annotations

import argparse
from typing import Optional, Sequence

from edge_landing.cli.common import CliParser, check_number, check_outputs_spare_inputs, check_threads, output_file, run_cli
from edge_landing.evaluation.scene import Scene
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.models import default_model_path
from edge_landing.runtime.perception.calibration_file import UNRELIABLE_SPREAD
from edge_landing.runtime.perception.inference import OnnxModel

from .scene_scale import CalibrationConfig, calibrate_scene


def build_parser() -> argparse.ArgumentParser:
    p = CliParser(prog="edge-calibrate", description=__doc__.split("\n\n")[0])
    p.add_argument("scene", help="scene folder with rgb/ and depth/")
    p.add_argument("--model", help="ONNX model (default: the shipped model)")
    p.add_argument("--out", help="output file (default: SCENE/calibration.json)")
    p.add_argument("--min-depth", type=float, default=None,
                   help="ground truth counted above this, metres (default: the model's contract min_depth)")
    p.add_argument("--max-depth", type=float, default=None,
                   help="ground truth counted below this, metres (default: the model's contract max_depth)")
    p.add_argument("--max-frames", type=int, default=None, help="use the first N frames only")
    p.add_argument("--threads", type=int, default=2, help="ONNX Runtime threads (default 2)")
    p.add_no_progress()
    return p


def _main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    if args.max_frames is not None and args.max_frames < 1:
        raise InputError(f"--max-frames must be at least 1, got {args.max_frames}")
    check_threads("--threads", args.threads)
    for flag, value in (("--min-depth", args.min_depth), ("--max-depth", args.max_depth)):
        if value is not None:
            check_number(flag, value, 0.0, lo_open=True, unit="metres")
    scene = Scene(args.scene)
    scene.require(depth=True, purpose="depth-scale calibration (edge-calibrate)")
    model_path = args.model if args.model else default_model_path()
    out_path = args.out if args.out else scene.path / "calibration.json"
    check_outputs_spare_inputs({"--out": out_path}, {"--model": model_path})
    out = output_file(out_path, "the --out file")
    model = OnnxModel.load(model_path, threads=args.threads)
    cal = calibrate_scene(scene, model, CalibrationConfig(args.min_depth, args.max_depth, args.max_frames),
                          show_progress=not args.no_progress)
    cal.save(out)
    print(f"scale {cal.scale:.4f} (MAD {cal.mad:.4f}, min {cal.min_ratio:.4f}, max {cal.max_ratio:.4f}) from "
          f"{cal.frames_used}/{cal.frames_total} frames; model {model.path.name} sha256 {cal.model_sha256[:12]}…")
    if not cal.reliable:
        print(f"warning: the frames disagree (MAD/scale = {cal.relative_spread:.3f} > {UNRELIABLE_SPREAD}); "
              f"one scale does not describe this scene well, prefer the in-flight altitude scale")
    print(f"wrote {out}")
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
