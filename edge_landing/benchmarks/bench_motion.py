"""Cost of the motion-geometry stage per frame, and its share of the pipeline (ARCHITECTURE.md §9, §11).

Renders the first frames of an ``edge-sim --flight`` flight (approach, the vehicle moving) at each camera
size, then times, on the same frames: the motion stage alone (``MotionStage.update``: keyframe pick,
plane warp, DIS on the window cropped around the network's spot, heights), the whole fusion with it
(``LandingFuser.update`` with the image) and the shipped model's inference (``--threads`` threads), after a
warm-up. Percentiles are over frames. Fusion is also split into frames with and without a stage run: the
frames without one are fusion's own per-frame cost with geometry confirmation in play (grid, geometry
evidence, spot choice), which bench_fusion's imageless scene never reaches. ``--network shipped`` feeds fusion
the shipped model's own output (its size, metric from the altitude), as edge-run does; the default, the
flat-lying model's planar depth at the camera's size, gives fusion more spots to confirm.
Thread pools as edge-run sets them (pipeline.threads): OpenCV at ``--opencv-threads`` (edge-run: 1), numpy's
BLAS at one thread: left at its default, OpenBLAS's idle threads spin after every small matrix product and take
a core from OpenCV's DIS and from the model.
The stage runs every ``geometry_interval_s`` of flight time, so its cost per frame depends on the camera's rate
(``--fps``, the flight's frame rate): a 30 frames/s camera pays it on one frame in six, 10 frames/s on one in two.

    python -m edge_landing.benchmarks.bench_motion --sizes 160x120 320x240 640x480
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from edge_landing.benchmarks.resolution_sweep import parse_size, refuse_negative_sizes
from edge_landing.cli.common import CliParser, check_choice, check_number, check_seed, check_threads, output_file, run_cli
from edge_landing.runtime.core.camera import Mount
from edge_landing.runtime.core.cpu_features import cpu_features
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import VehicleState
from edge_landing.runtime.fusion.deferred import StageTiming
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
from edge_landing.runtime.fusion.motion import CameraPose
from edge_landing.runtime.pipeline.threads import SideThreads, limit_side_threads

FLIGHT_FRAMES = 200     # the rendered flight's length: --warmup + --frames come from its start


def _pct(ms: list[float]) -> dict[str, float]:
    a = np.asarray(ms)
    return {"p50": float(np.percentile(a, 50)), "p90": float(np.percentile(a, 90)), "p99": float(np.percentile(a, 99)),
            "mean": float(np.mean(a))}


def bench_size(width: int, height: int, frames: int, warmup: int, threads: int, style: str, seed: int,
               fps: float = 10.0, opencv_threads: int = 1, network: str = "lying",
               timing: StageTiming = StageTiming.INLINE, paced: bool = False) -> dict[str, Any]:
    from edge_landing import sim
    from edge_landing.benchmarks.lying_model import lying_prediction
    from edge_landing.runtime.models import default_model_path
    from edge_landing.runtime.perception.inference import OnnxModel
    from edge_landing.runtime.perception.scale import AltitudeScaleEstimator
    from edge_landing.runtime.pipeline import ScaleStage
    from edge_landing.sim.generate import SimConfig, render_sample, vehicle_samples

    scfg = SimConfig(out=Path("."), frames=FLIGHT_FRAMES, style=sim.Style.from_string(style), seed=seed, flight=True,
                     fps=fps, width=width, height=height)
    world = sim.build_world(scfg.style, seed, hazards=True)
    mount, intr = Mount(), scfg.intrinsics
    renderer = sim.Renderer(world, intr, mount)
    shots = []
    for k, s in enumerate(vehicle_samples(scfg, world)):
        if k >= warmup + frames:
            break
        shots.append((s, render_sample(scfg, k, s, renderer).rgb))
    limit_side_threads(SideThreads(opencv=opencv_threads, blas=1))
    fuser = LandingFuser(FusionConfig(geometry_timing=timing), intr, mount)
    model = OnnxModel.load(default_model_path(), threads)
    scale = ScaleStage(None, AltitudeScaleEstimator(), intr, mount)
    stage_ms, fusion_ms, model_ms, ran, run_ms = [], [], [], [], []
    start = time.perf_counter()
    for k, (s, rgb) in enumerate(shots):
        state = VehicleState(s.t_s, s.attitude, s.position_ned_m.copy(), s.agl_m, "sim")
        if paced:       # frames arrive at the camera's rate, as live: the time between is the CPU's to spare
            time.sleep(max(0.0, start + k / fps - time.perf_counter()))
        t0 = time.perf_counter()
        own = model.predict(rgb, k, s.t_s)
        t1 = time.perf_counter()
        # "shipped": fusion gets the model's own output at its own size, metric from the altitude, as in edge-run.
        pred = scale.apply(own, state) if network == "shipped" else lying_prediction(intr, mount, state, k)
        t2 = time.perf_counter()
        target = fuser.update(pred, state, s.t_s, rgb)
        t3 = time.perf_counter()
        if k >= warmup:
            fusion_ms.append(1e3 * (t3 - t2))
            model_ms.append(1e3 * (t1 - t0))
            stage_ms.append(1e3 * target.timings_s.get("geometry", float("nan")))
            ran.append(fuser.geometry_ran)
            if "geometry_stage" in target.timings_s:
                run_ms.append(1e3 * target.timings_s["geometry_stage"])
    # The stage alone, on the same frames, from a fresh keyframe ring (no fusion around it).
    alone = LandingFuser(FusionConfig(), intr, mount).motion
    alone_ms = []
    for k, (s, rgb) in enumerate(shots):
        pose = CameraPose.of(mount, s.attitude, s.position_ned_m, s.agl_m)
        t0 = time.perf_counter()
        alone.update(rgb, pose, s.t_s)
        if k >= warmup:
            alone_ms.append(1e3 * (time.perf_counter() - t0))
    window = list(alone.config.window_hw)
    # Shares of means: the stage runs every geometry_interval_s, so its p50 over frames says little alone.
    stage, total = _pct(stage_ms), float(np.mean(np.asarray(fusion_ms) + np.asarray(model_ms)))
    # Fusion's own cost (grid, geometry evidence, spot choice) on frames without a stage run, and with one.
    fused, stage_ran = np.asarray(fusion_ms), np.asarray(ran, dtype=bool)
    split = {key: _pct(list(fused[mask])) if mask.any() else None
             for key, mask in (("fusion_without_stage_run_ms", ~stage_ran), ("fusion_with_stage_run_ms", stage_ran))}
    return {"size": f"{width}x{height}", "window_hw": window, "frames": frames, "threads": threads, "fps": fps,
            "network": network, "geometry_timing": str(timing), "paced": paced,
            "stage_run_ms": _pct(run_ms) if run_ms else None,
            "opencv_threads": opencv_threads, "cpu": cpu_features().summary(),
            "stage_in_fusion_ms": stage, "stage_alone_ms": _pct(alone_ms), "fusion_ms": _pct(fusion_ms),
            "model_ms": _pct(model_ms), "stage_share_of_model_plus_fusion": stage["mean"] / total,
            "stage_runs": int(stage_ran.sum()), **split}


def _main(argv: Optional[Sequence[str]] = None) -> int:
    p = CliParser(prog="bench_motion", description=__doc__.split("\n\n")[0],
                  formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", nargs="+", default=["160x120", "320x240", "640x480"], help="camera sizes WxH")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--warmup", type=int, default=10)
    p.add_argument("--threads", type=int, default=2, help="ONNX Runtime threads for the model")
    p.add_argument("--opencv-threads", type=int, default=1, help="OpenCV threads (edge-run uses 1)")
    p.add_argument("--fps", type=float, default=10.0, help="the flight's frame rate (the camera's)")
    p.add_argument("--style", default="suburban")
    p.add_argument("--seed", type=int, default=41)
    p.add_argument("--network", choices=("lying", "shipped"), default="lying",
                   help="what fusion gets: the flat-lying model's planar depth at the camera's size (more spots to "
                        "confirm), or the shipped model's own output, metric from the altitude (as edge-run runs it)")
    p.add_argument("--geometry-timing", default="inline", help="inline: the stage inside the frame that runs it; "
                   "overlapped (edge-run's default): on its own thread, collected by the next frame (fusion.deferred)")
    p.add_argument("--paced", action="store_true", help="feed frames at --fps as a live camera does (default: "
                   "back to back, the CPU never idle)")
    p.add_argument("--json", help="write the results here")
    refuse_negative_sizes(argv)
    a = p.parse_args(argv)
    if a.frames < 1:
        raise InputError(f"--frames must be at least 1, got {a.frames}")
    check_threads("--threads", a.threads)
    check_threads("--opencv-threads", a.opencv_threads)
    check_number("--fps", a.fps, 0.1, 240.0, unit="frames/s")
    if a.warmup < 0:
        raise InputError(f"--warmup must be >= 0, got {a.warmup}")
    if a.frames + a.warmup > FLIGHT_FRAMES:
        raise InputError(f"--frames + --warmup must be <= {FLIGHT_FRAMES} (the flight's frames), got "
                         f"{a.frames} + {a.warmup}")
    check_seed("--seed", a.seed)
    from edge_landing.sim.world import Style

    check_choice("--style", Style.from_string, a.style)
    timing = StageTiming.from_string(a.geometry_timing)
    results = []
    sizes = [parse_size(s) for s in a.sizes]          # all checked before the first (slow) render
    json_path = output_file(a.json, "the --json file") if a.json else None
    for w, h in sizes:
        r = bench_size(w, h, a.frames, a.warmup, a.threads, a.style, a.seed, a.fps, a.opencv_threads, a.network,
                       timing, a.paced)
        results.append(r)
        s, f, m = r["stage_alone_ms"], r["fusion_ms"], r["model_ms"]
        i = r["stage_in_fusion_ms"]
        print(f"{r['size']:>8s} at {r['fps']:g} frames/s, geometry {r['geometry_timing']}"
              f"{', paced' if r['paced'] else ''} (DIS window <= {r['window_hw'][0]}x{r['window_hw'][1]}): "
              f"stage alone (every frame) "
              f"p50 {s['p50']:.2f} p90 {s['p90']:.2f} p99 {s['p99']:.2f} ms; in fusion (every "
              f"{FusionConfig().geometry_interval_s:g} s) mean {i['mean']:.2f} p50 {i['p50']:.2f} p90 {i['p90']:.2f} ms; "
              f"fusion with it p50 {f['p50']:.2f} ms, model p50 "
              f"{m['p50']:.2f} ms; stage = {100 * r['stage_share_of_model_plus_fusion']:.0f} % of model + fusion (means)",
              flush=True)
        if r["stage_run_ms"] is not None and timing is StageTiming.OVERLAPPED:
            q = r["stage_run_ms"]
            print(f"{'':>8s} stage runs on their own thread: p50 {q['p50']:.2f} p90 {q['p90']:.2f} ms", flush=True)
        for key, what in (("fusion_without_stage_run_ms", "without"), ("fusion_with_stage_run_ms", "with")):
            q = r[key]
            if q is not None:
                print(f"{'':>8s} fusion on frames {what} a stage run: p50 {q['p50']:.2f} p90 {q['p90']:.2f} "
                      f"p99 {q['p99']:.2f} ms", flush=True)
    if json_path is not None:
        json_path.write_text(json.dumps(results, indent=1))
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
