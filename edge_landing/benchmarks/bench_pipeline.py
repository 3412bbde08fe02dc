"""Whole-pipeline throughput vs model-only throughput, same run, 2 threads (ARCHITECTURE.md §9; goal: pipeline >= 90 %).

The frames are read (or rendered by the simulator) into memory first, so neither camera nor renderer is
timed. Each round runs, in rotating order, (a) the model alone over every frame, (b) the full pipeline
(telemetry match, inference, in-flight scale, fusion, LANDING_TARGET to a loopback UDP socket, decision log)
with fusion overlapping the next inference, (c) the same pipeline strictly sequential. Ratios are taken
between modes of the same round, so a noisy shared machine moves all of them together.

    python -m edge_landing.benchmarks.bench_pipeline --frames 40 --rounds 3            # sim frames, shipped model
    python -m edge_landing.benchmarks.bench_pipeline --camera flight.mp4 --model m.onnx --out bench.json
    python -m edge_landing.benchmarks.bench_pipeline --depth-model small_depth.int8.onnx --hvo-model small_hvo.int8.onnx
"""
from __future__ import annotations

import io
import json
import math
import socket
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from edge_landing.cli.common import CliParser, check_outputs_spare_inputs, check_threads, output_file, run_cli
from edge_landing.runtime.core.camera import Intrinsics, Mount
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import VehicleState
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
from edge_landing.runtime.io.grabber import Grabber
from edge_landing.runtime.io.mavlink_link import LinkConfig, MavlinkLink
from edge_landing.runtime.io.sources import Reader, SourceConfig, SourceKind
from edge_landing.runtime.io.telemetry import TelemetryBuffer
from edge_landing.runtime.perception.backend import Runtime
from edge_landing.runtime.perception.inference import OnnxModel, SessionConfig
from edge_landing.runtime.perception.scale import AltitudeScaleEstimator
from edge_landing.runtime.pipeline import (
    JointInference,
    PairInference,
    Pipeline,
    PipelineOptions,
    ScaleStage,
)
from edge_landing.runtime.pipeline.threads import limit_side_threads

MODES = ("model-only", "pipeline-overlap", "pipeline-sequential", "pipeline-rate")


@dataclass(frozen=True)
class BenchConfig:
    model: Optional[str] = None
    camera: str = "sim"
    depth_model: Optional[str] = None   # with hvo_model: a depth + HVO pair instead of one joint model
    hvo_model: Optional[str] = None
    frames: int = 40
    width: int = 640
    height: int = 480
    threads: int = 2
    rounds: int = 3
    warmup: int = 3
    out: Optional[str] = None
    fusion_hz: float = 15.0   # the pipeline-rate mode fuses at most this often (edge-run --fusion-hz)
    runtime: Runtime = Runtime.ONNXRUNTIME   # the runtime that runs the given file(s) (edge-run --runtime)
    cap_side_threads: bool = True   # OpenCV and BLAS at 1 thread each, as edge-run sets them


class MemoryReader(Reader):
    """Replays frames held in memory (with their simulated vehicle states) as a recorded input."""

    def __init__(self, frames: list):
        self.frames, self.i, self.last_state, self.name = frames, 0, None, "memory"

    def read(self):
        if self.i >= len(self.frames):
            return None
        rgb, self.last_state = self.frames[self.i]
        self.i += 1
        return rgb


def load_frames(cfg: BenchConfig):
    """(list of (rgb, VehicleState or None), intrinsics, mount)."""
    from tqdm import tqdm

    if cfg.camera.startswith("sim"):
        from edge_landing import sim

        cam = sim.SimCamera(seed=0, width=cfg.width, height=cfg.height, fps=10.0)
        frames: list[tuple[np.ndarray, Optional[VehicleState]]] = [
            cam.read()[::2] for _ in tqdm(range(cfg.frames), desc="rendering sim frames", unit="frame")]
        return frames, cam.intrinsics, cam.mount
    grabber = Grabber(SourceConfig.from_string(cfg.camera)).start()
    frames = []
    while len(frames) < cfg.frames and (f := grabber.next(timeout_s=2.0)) is not None:
        frames.append((f.rgb, None))
    grabber.stop()
    if not frames:
        raise InputError(f"{cfg.camera} gave no frames")
    h, w = frames[0][0].shape[:2]
    return frames, Intrinsics.from_hfov(w, h), Mount()


def model_only(inference, frames: list) -> tuple:
    from edge_landing.runtime.core.messages import Frame

    lat = []
    start = time.perf_counter()
    for i, (rgb, _) in enumerate(frames):
        t0 = time.perf_counter()
        inference.predict(Frame(i, time.monotonic(), rgb))
        lat.append(time.perf_counter() - t0)
    return time.perf_counter() - start, lat


def pipeline_once(inference, frames, intrinsics, mount, overlap: bool, sink_port: int,
                  fusion_hz: float = 0.0) -> tuple:
    telemetry = TelemetryBuffer()
    link = MavlinkLink(LinkConfig(f"udpout:127.0.0.1:{sink_port}"), telemetry).start()
    grabber = Grabber(SourceConfig("memory", SourceKind.FILE), opener=lambda c: MemoryReader(frames),
                      telemetry=telemetry).start()
    fuser = LandingFuser(FusionConfig(), intrinsics, mount)
    scale = ScaleStage(None, AltitudeScaleEstimator(), intrinsics, mount)
    pipe = Pipeline(grabber, inference, scale, fuser.fuse, telemetry, link,
                    PipelineOptions(status_period_s=1e9, overlap=overlap, fusion_max_hz=fusion_hz),
                    io.StringIO(), None, io.StringIO())
    try:
        summary = pipe.run()
    finally:
        grabber.stop()
        link.stop()
    return summary.wall_s, summary.times.all["total"], summary


def percentiles_ms(values: Sequence[float]) -> dict:
    p = np.percentile(np.asarray(values) * 1e3, (50, 90, 99)) if values else [math.nan] * 3
    return {"p50_ms": round(float(p[0]), 2), "p90_ms": round(float(p[1]), 2), "p99_ms": round(float(p[2]), 2)}


def bench(cfg: BenchConfig) -> dict:
    from tqdm import tqdm

    from edge_landing.runtime.models import default_model_path

    if cfg.cap_side_threads:
        limit_side_threads()
    inference: PairInference | JointInference
    session = SessionConfig(threads=cfg.threads, runtime=cfg.runtime)
    if cfg.depth_model and cfg.hvo_model:
        inference = PairInference(OnnxModel.load(cfg.depth_model, config=session),
                                  OnnxModel.load(cfg.hvo_model, config=session))
        model = inference.depth_model
    else:
        model = OnnxModel.load(cfg.model or default_model_path(), config=session)
        inference = JointInference(model)
    frames, intrinsics, mount = load_frames(cfg)
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # a listener, so LANDING_TARGET really goes out
    sink.bind(("127.0.0.1", 0))
    sink.setblocking(False)
    from edge_landing.runtime.core.messages import Frame

    for i, (rgb, _) in enumerate(frames[: cfg.warmup]):
        inference.predict(Frame(i, time.monotonic(), rgb))
    walls: dict[str, list[float]] = {m: [] for m in MODES}
    cpus: dict[str, list[float]] = {m: [] for m in MODES}   # process CPU seconds: the real cost, whatever else the machine runs
    lats: dict[str, list[float]] = {m: [] for m in MODES}
    fused: dict[str, list[int]] = {m: [] for m in MODES}   # frames that reached fusion (a target update each)
    targets = 0
    for r in tqdm(range(cfg.rounds), desc="rounds (model-only / overlap / sequential)", unit="round"):
        order = MODES[r % len(MODES):] + MODES[: r % len(MODES)]  # rotate so no mode always runs first on a warm cache
        for mode in order:
            cpu0 = time.process_time()
            if mode == "model-only":
                wall, lat = model_only(inference, frames)
            else:
                wall, lat, summary = pipeline_once(inference, frames, intrinsics, mount,
                                                   mode != "pipeline-sequential", sink.getsockname()[1],
                                                   cfg.fusion_hz if mode == "pipeline-rate" else 0.0)
                targets = max(targets, summary.targets)
                fused[mode].append(summary.frames - summary.not_fused)
            walls[mode].append(wall)
            cpus[mode].append(time.process_time() - cpu0)
            lats[mode].extend(lat)
            _drain(sink)
    sink.close()
    n = len(frames)
    rows = {m: {"images_per_s": round(n * len(walls[m]) / sum(walls[m]), 2),
                "per_round_images_per_s": [round(n / w, 2) for w in walls[m]],
                "cpu_ms_per_frame": round(1e3 * sum(cpus[m]) / (n * len(cpus[m])), 2), **percentiles_ms(lats[m])}
            for m in MODES}
    for m in MODES[1:]:
        rows[m]["fused_per_s"] = round(sum(fused[m]) / sum(walls[m]), 2)  # how often targets update
        ratios = [walls["model-only"][i] / walls[m][i] for i in range(cfg.rounds)]
        rows[m]["ratio_to_model"] = round(float(np.median(ratios)), 3)
    return {"config": asdict(cfg), "model": inference.name, "frames": n, "frame_size": list(frames[0][0].shape[:2]),
            "model_input": [model.contract.input.height, model.contract.input.width], "targets_last_round": targets,
            "modes": rows}


def _drain(sock: socket.socket) -> None:
    try:
        while sock.recv(4096):
            pass
    except BlockingIOError:
        pass


def report(result: dict) -> str:
    lines = [f"model {result['model']} | {result['frames']} frames {result['frame_size'][1]}x{result['frame_size'][0]} "
             f"| input {result['model_input'][1]}x{result['model_input'][0]} | {result['config']['threads']} threads "
             f"| {result['config']['runtime']} | OpenCV/BLAS threads "
             f"{'1/1 (as edge-run)' if result['config']['cap_side_threads'] else 'library defaults'}",
             "| mode | images/s | target updates/s | p50 ms | p90 ms | p99 ms | CPU ms/frame | vs model-only |",
             "|---|---|---|---|---|---|---|---|"]
    for mode, r in result["modes"].items():
        ratio = f"{r['ratio_to_model']:.0%}" if "ratio_to_model" in r else "-"
        updates = f"{r['fused_per_s']:.1f}" if "fused_per_s" in r else "-"
        lines.append(f"| {mode} | {r['images_per_s']:.2f} | {updates} | {r['p50_ms']:.1f} | {r['p90_ms']:.1f} "
                     f"| {r['p99_ms']:.1f} | {r['cpu_ms_per_frame']:.1f} | {ratio} |")
    lines.append("latency: model-only = one predict; pipeline = telemetry match to decision logged (end to end); "
                 "vs model-only = median over rounds of the per-round images/s ratio; pipeline-rate fuses at most "
                 f"{result['config']['fusion_hz']:g} frames/s (edge-run --fusion-hz), the others are inferred only")
    return "\n".join(lines)


def _main(argv: Optional[Sequence[str]] = None) -> int:
    p = CliParser(prog="bench_pipeline", description=__doc__.split("\n\n")[0])
    p.add_argument("--model", help="joint depth+HVO model (default: the shipped edgenet)")
    p.add_argument("--depth-model", help="depth model of a pair (with --hvo-model)")
    p.add_argument("--hvo-model", help="HVO model of a pair (with --depth-model)")
    p.add_argument("--camera", default="sim", help="'sim' (rendered into memory first), a video or an image folder")
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--size", default="640x480", help="sim frame size WxH (edge-run's sim camera: 640x480)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--fusion-hz", type=float, default=15.0, help="the pipeline-rate mode's fusion cap")
    p.add_argument("--runtime", default="onnxruntime", help="onnxruntime (default) or openvino: what runs the file(s)")
    p.add_argument("--library-thread-defaults", action="store_true",
                   help="leave OpenCV's and BLAS's own thread pools as they come (edge-run caps both at 1)")
    p.add_argument("--out", help="write the result as JSON")
    a = p.parse_args(argv)
    try:
        w, h = (int(v) for v in a.size.lower().split("x"))
    except ValueError:
        raise InputError(f"--size must look like 320x240, got '{a.size}'") from None
    if not (16 <= w <= 4096 and 16 <= h <= 4096):
        raise InputError(f"--size {a.size}: width and height must be 16..4096 pixels")
    if not 10 <= a.fusion_hz <= 1000:
        raise InputError(f"--fusion-hz must be 10-1000 (targets must update at 10 Hz or faster), got {a.fusion_hz}")
    for flag, value in (("--frames", a.frames), ("--rounds", a.rounds)):
        if value < 1:
            raise InputError(f"{flag} must be at least 1, got {value}")
    check_threads("--threads", a.threads)
    if bool(a.depth_model) != bool(a.hvo_model):
        raise InputError("--depth-model and --hvo-model go together")
    if a.model and a.depth_model:
        raise InputError("--model and --depth-model/--hvo-model are alternatives: give one")
    if SourceKind.from_string(a.camera) is SourceKind.FILE and not Path(a.camera).is_file():
        raise InputError(f"--camera {a.camera} does not exist (expected 'sim', a video, an image folder or a device)")
    try:
        runtime = Runtime.from_string(a.runtime)
    except InputError as exc:
        raise InputError(f"--runtime: {exc}") from None
    check_outputs_spare_inputs({"--out": a.out}, {"--model": a.model, "--depth-model": a.depth_model,
                                                   "--hvo-model": a.hvo_model, "--camera": a.camera})
    if a.out:
        output_file(a.out, "the --out file")
    cfg = BenchConfig(a.model, a.camera, a.depth_model, a.hvo_model, a.frames, w, h, a.threads, a.rounds, out=a.out,
                      fusion_hz=a.fusion_hz, runtime=runtime,
                      cap_side_threads=not a.library_thread_defaults)
    result = bench(cfg)
    print(report(result))
    if cfg.out:
        with open(cfg.out, "w") as fh:
            json.dump(result, fh, indent=2)
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    sys.exit(main())
