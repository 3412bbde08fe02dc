"""What a camera frame costs before and around the network, per image size (issue 17, ARCHITECTURE.md §9).

For each size: decoding one frame of an mp4v video (cv2.VideoCapture, what ``edge-run --camera file.mp4``
does), BGR->RGB conversion (every source does it), the model's preprocessing (resize or letterbox to the
input, normalisation: ``OnnxModel.prepare``), the network itself and the decoding of its outputs (cropped to
the image part). ONNX Runtime and OpenCV get ``threads`` threads (the drone has 2 cores); every stage is
warmed up, then timed ``iterations`` times, frames cycling through a short clip. Prints a markdown table
(p50/p90/p99 ms per stage and size) and, with ``--json``, the numbers.

    python -m edge_landing.benchmarks.frame_cost --sizes 320x240 640x480 1280x720 1920x1080

The clip is a synthetic-town frame (edge-sim) panned a few pixels per frame, so the codec sees real texture
and motion; a live camera's decode happens in its driver or hardware instead, so that row is an upper bound.
"""
from __future__ import annotations

import json
import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from edge_landing.cli.common import run_cli
from edge_landing.runtime.core.errors import InputError

STAGES = ("decode", "colour", "preprocess", "inference", "outputs")


@dataclass(frozen=True)
class CostConfig:
    sizes: Tuple[Tuple[int, int], ...] = ((320, 240), (640, 480), (1280, 720))   # (width, height)
    threads: int = 2
    warmup: int = 5
    iterations: int = 40
    clip_frames: int = 20
    model: Optional[str] = None


def _source_image(width: int, height: int) -> np.ndarray:
    """One synthetic-town RGB frame (sim) at the largest size asked for, or a textured pattern without sim."""
    try:
        from edge_landing import sim
        from edge_landing.runtime.core.camera import Intrinsics, Mount
        from edge_landing.sim.effects import Effects

        world = sim.build_world("urban", 1)
        renderer = sim.Renderer(world, Intrinsics.from_hfov(width, height), Mount())
        view = sim.random_view(world, np.random.default_rng(0))
        return renderer.render(view.position_ned_m, view.attitude, Effects(), np.random.default_rng(1)).rgb
    except ImportError:                       # no [sim] extra: still a fair load for the codec
        rng = np.random.default_rng(0)
        small = rng.integers(0, 256, (height // 8 + 1, width // 8 + 1, 3), np.uint8)
        import cv2

        return cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)


def write_clip(path: Path, base_rgb: np.ndarray, width: int, height: int, frames: int) -> Path:
    import cv2

    img = cv2.resize(base_rgb, (width, height), interpolation=cv2.INTER_AREA)
    video = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), 10.0, (width, height))
    if not video.isOpened():
        raise InputError(f"cannot write an mp4v video at {path} (OpenCV without an MP4 encoder?)")
    step = max(1, width // 160)
    for k in range(frames):
        video.write(cv2.cvtColor(np.roll(img, k * step, axis=1), cv2.COLOR_RGB2BGR))
    video.release()
    return path


def _time(fn: Callable[[], object], warmup: int, iterations: int) -> List[float]:
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(iterations):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def measure_size(model: Any, clip: Path, config: CostConfig) -> Dict[str, List[float]]:
    """Seconds per call of every stage for the frames of ``clip``."""
    import cv2

    cap = cv2.VideoCapture(str(clip))

    def decode() -> np.ndarray:
        ok, bgr = cap.read()
        if not ok:                                   # cycle the clip
            cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            ok, bgr = cap.read()
        if not ok or bgr is None:
            raise InputError(f"cannot decode {clip} (OpenCV without an MP4 decoder?)")
        return bgr

    bgr = decode()
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    tensor = model.prepare(rgb)
    outputs = model.run(tensor)
    fit = model.fit(rgb.shape[:2])
    times = {"decode": _time(decode, config.warmup, config.iterations),
             "colour": _time(lambda: cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), config.warmup, config.iterations),
             "preprocess": _time(lambda: model.prepare(rgb), config.warmup, config.iterations),
             "inference": _time(lambda: model.run(tensor), config.warmup, config.iterations),
             "outputs": _time(lambda: model.decode(outputs, fit=fit), config.warmup, config.iterations)}
    cap.release()
    return times


def measure(config: CostConfig) -> List[Dict[str, Any]]:
    import cv2

    from edge_landing.runtime.models import default_model_path
    from edge_landing.runtime.perception.inference import OnnxModel

    cv2.setNumThreads(config.threads)
    model = OnnxModel.load(config.model or default_model_path(), threads=config.threads)
    big_w = max(w for w, _ in config.sizes)
    big_h = max(h for _, h in config.sizes)
    base = _source_image(big_w, big_h)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for width, height in config.sizes:
            clip = write_clip(Path(tmp) / f"clip_{width}x{height}.mp4", base, width, height, config.clip_frames)
            times = measure_size(model, clip, config)
            total = [sum(v) for v in zip(*(times[s] for s in STAGES))]
            row = {"width": width, "height": height, "threads": config.threads,
                   "stages": {s: _pct(times[s]) for s in STAGES}, "sum": _pct(total)}
            rows.append(row)
    return rows


def _pct(values: Sequence[float]) -> Dict[str, float]:
    a = np.asarray(values) * 1e3
    return {"p50_ms": float(np.percentile(a, 50)), "p90_ms": float(np.percentile(a, 90)),
            "p99_ms": float(np.percentile(a, 99))}


def table(rows: List[Dict[str, Any]]) -> str:
    head = "| size | " + " | ".join(f"{s} p50/p90/p99 ms" for s in (*STAGES, "sum")) + " |"
    lines = [head, "|" + "---|" * (len(STAGES) + 2)]
    for r in rows:
        cells = [r["stages"][s] for s in STAGES] + [r["sum"]]
        lines.append(f"| {r['width']}×{r['height']} | " + " | ".join(
            f"{c['p50_ms']:.2f} / {c['p90_ms']:.2f} / {c['p99_ms']:.2f}" for c in cells) + " |")
    return "\n".join(lines)


def _main(argv: Optional[Sequence[str]] = None) -> int:
    from edge_landing.benchmarks.resolution_sweep import parse_size, refuse_negative_sizes
    from edge_landing.cli.common import CliParser, check_outputs_spare_inputs, check_threads, output_file

    p = CliParser(prog="frame_cost", description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", nargs="+", default=["320x240", "640x480", "1280x720"])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--iterations", type=int, default=40)
    p.add_argument("--model", help="ONNX model (default: the shipped edgenet)")
    p.add_argument("--json", help="also write the numbers here")
    refuse_negative_sizes(argv)
    a = p.parse_args(argv)
    check_threads("--threads", a.threads)
    if a.iterations < 1:
        raise InputError(f"--iterations must be at least 1, got {a.iterations}")
    if a.warmup < 0:
        raise InputError(f"--warmup must be >= 0, got {a.warmup}")
    if a.model and not Path(a.model).is_file():
        raise InputError(f"--model file {a.model} does not exist")
    sizes = tuple(parse_size(s) for s in a.sizes)
    check_outputs_spare_inputs({"--json": a.json}, {"--model": a.model})
    json_path = output_file(a.json, "the --json file") if a.json else None
    rows = measure(CostConfig(sizes, a.threads, a.warmup, a.iterations, model=a.model))
    print(table(rows))
    if json_path is not None:
        json_path.write_text(json.dumps(rows, indent=1))
    return 0 if all(math.isfinite(r["sum"]["p50_ms"]) for r in rows) else 1


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
