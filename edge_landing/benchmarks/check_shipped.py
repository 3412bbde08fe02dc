"""A new user's check of the shipped model, independent of the runtime's own code paths.

Renders fresh scenes with the ``edge-sim`` command (as ``python -m edge_landing.sim.cli``; seeds of the user's
choosing), then reads the model's layout from its ONNX metadata by hand and runs it with a plain ONNX Runtime
session: its own preprocessing (OpenCV resize, scale, mean/std, layout), its own depth decoding and its own metrics. Nothing from
``edge_landing.runtime.perception.inference``, ``edge_landing.evaluation.metrics`` or
``edge_landing.evaluation.evaluate`` is used, so an error there cannot hide here.

    python -m edge_landing.benchmarks.check_shipped --seeds suburban:901 urban:902 --frames 40 --out out/check_shipped

Prints one row per scene and model and writes OUT/check.json. Goals (issue 7): horizontal precision >= 0.90
and δ1 >= 0.80 after one per-scene median scale, on both styles.
"""
from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Sequence

import cv2
import numpy as np
import onnxruntime as ort

from edge_landing.cli.common import CliParser, check_outputs_spare_inputs, output_folder, run_cli
from edge_landing.runtime.core.errors import InputError

MODELS = Path(__file__).resolve().parents[1] / "runtime" / "models"
GOAL_H_PRECISION, GOAL_DELTA1 = 0.90, 0.80


@dataclass(frozen=True)
class SceneSpec:
    style: str
    seed: int

    @classmethod
    def parse(cls, text: str) -> SceneSpec:
        style, _, seed = text.partition(":")
        if style not in ("suburban", "urban") or not seed.isdigit():
            raise InputError(f"--seeds: scene '{text}' is not STYLE:SEED (style suburban or urban, seed >= 0)")
        return cls(style, int(seed))


def render(spec: SceneSpec, frames: int, root: Path) -> Path:
    out = root / f"{spec.style}{spec.seed}"
    if not (out / "scene.json").is_file():
        proc = subprocess.run([sys.executable, "-m", "edge_landing.sim.cli", str(out), "--frames", str(frames),
                               "--style", spec.style, "--seed", str(spec.seed), "--no-progress", "--no-normals"],
                              stderr=subprocess.PIPE, text=True)
        if proc.returncode != 0:
            last = (proc.stderr.strip().splitlines() or [f"exit status {proc.returncode}"])[-1]
            raise InputError(f"edge-sim could not render {spec.style}:{spec.seed} into {out}: {last}")
    return out


class PlainModel:
    """The ONNX file run exactly as its metadata says, with nothing but onnxruntime, numpy and OpenCV."""

    def __init__(self, path: Path):
        if not path.is_file():
            raise InputError(f"--models: model file {path} {'is a folder' if path.is_dir() else 'does not exist'}; "
                             "expected an ONNX file from edge-export/edge-train")
        try:
            self.session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own untyped errors for unreadable files
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise InputError(f"--models: {path} is not a loadable ONNX model ({first[:200]})") from None
        meta = self.session.get_modelmeta().custom_metadata_map
        try:
            self.inp, self.depth, self.hvo = (json.loads(meta[k]) for k in ("edge.input", "edge.depth", "edge.hvo"))
            convention = self.depth["convention"]
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"--models: {path} has no edge depth+HVO contract in its metadata ({exc!r})") from None
        if convention != "metric":
            raise InputError(f"--models: {path} has depth convention {convention}; this check decodes 'metric' only")

    def run(self, rgb: np.ndarray):
        """rgb H×W×3 uint8 → (depth metres, HVO labels), both at the image's own size."""
        h, w = self.inp["height"], self.inp["width"]
        x = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
        if self.inp["color"] == "BGR":
            x = x[..., ::-1]
        x = (x * self.inp["scale"] - np.float32(self.inp["mean"])) / np.float32(self.inp["std"])
        x = x.transpose(2, 0, 1)[None] if self.inp["layout"] == "NCHW" else x[None]
        outs = dict(zip([o.name for o in self.session.get_outputs()],
                        self.session.run(None, {self.inp["name"]: np.ascontiguousarray(x, np.float32)})))
        depth = outs[self.depth["output"]][0]
        depth = depth[0] if self.depth["layout"] == "NCHW" else depth[..., 0]
        logits = outs[self.hvo["output"]][0]
        labels = (logits.argmax(axis=0) if self.hvo["layout"] == "NCHW" else logits.argmax(axis=-1)).astype(np.uint8)
        size = (rgb.shape[1], rgb.shape[0])
        return (cv2.resize(depth.astype(np.float32), size, interpolation=cv2.INTER_LINEAR),
                cv2.resize(labels, size, interpolation=cv2.INTER_NEAREST))


def score(model: PlainModel, scene: Path) -> Dict[str, float]:
    lo, hi = model.depth["min_depth"], model.depth["max_depth"]
    ids = sorted(p.stem for p in (scene / "rgb").glob("*.png"))
    tp = fp = 0
    gts, preds = [], []
    for fid in ids:
        bgr = cv2.imread(str(scene / "rgb" / f"{fid}.png"))
        assert bgr is not None, f"{scene}/rgb/{fid}.png is not a readable image"   # listed by the glob above
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        gt = np.load(scene / "depth" / f"{fid}.npy")
        labels = cv2.imread(str(scene / "hvo" / f"{fid}.png"), cv2.IMREAD_UNCHANGED)
        depth, pred_labels = model.run(rgb)
        known = labels != 255
        tp += int(np.sum(known & (pred_labels == 0) & (labels == 0)))
        fp += int(np.sum(known & (pred_labels == 0) & (labels != 0)))
        ok = np.isfinite(gt) & (gt > lo) & (gt < hi) & np.isfinite(depth) & (depth > 0)
        gts.append(gt[ok].astype(np.float64))
        preds.append(depth[ok].astype(np.float64))
    scale = float(np.median([np.median(g) / np.median(p) for g, p in zip(gts, preds)]))
    d1_scene = [np.mean(np.maximum(g / (p * scale), p * scale / g) < 1.25) for g, p in zip(gts, preds)]
    d1_image = [np.mean(np.maximum(g / (p * s), p * s / g) < 1.25)
                for g, p in zip(gts, preds) for s in [np.median(g) / np.median(p)]]
    return {"frames": len(ids), "h_precision": tp / max(1, tp + fp), "delta1_scene_scale": float(np.mean(d1_scene)),
            "delta1_image_scale": float(np.mean(d1_image)), "scene_scale": scale}


def _main(argv: Sequence[str] | None = None) -> int:
    p = CliParser(prog="check_shipped", description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", nargs="+", default=["suburban:901", "urban:902"], help="STYLE:SEED scenes to render")
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--models", nargs="+", type=Path, default=[MODELS / "edgenet.onnx", MODELS / "edgenet.int8.onnx"])
    p.add_argument("--out", type=Path, default=Path("out/check_shipped"))
    args = p.parse_args(argv)
    specs = [SceneSpec.parse(s) for s in args.seeds]
    if args.frames < 1:
        raise InputError(f"--frames must be at least 1, got {args.frames}")
    models = {path: PlainModel(path) for path in args.models}    # every model checked before the first render
    check_outputs_spare_inputs({"--out": args.out / "check.json"}, {f"--models {m}": m for m in args.models})
    output_folder(args.out, "the --out folder")
    rows: List[dict] = []
    for spec in specs:
        scene = render(spec, args.frames, args.out)
        for path, model in models.items():
            r = {"model": path.name, "scene": f"{spec.style} seed {spec.seed}", **score(model, scene)}
            r["meets_goals"] = r["h_precision"] >= GOAL_H_PRECISION and r["delta1_scene_scale"] >= GOAL_DELTA1
            rows.append(r)
            print(f"{r['model']:<20} {r['scene']:<20} H precision {r['h_precision']:.3f}  "
                  f"δ1 (scene scale) {r['delta1_scene_scale']:.3f}  δ1* {r['delta1_image_scale']:.3f}  "
                  f"{'meets' if r['meets_goals'] else 'MISSES'} the goals", flush=True)
    (args.out / "check.json").write_text(json.dumps(rows, indent=1))
    return 0 if all(r["meets_goals"] for r in rows) else 1


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    sys.exit(main())
