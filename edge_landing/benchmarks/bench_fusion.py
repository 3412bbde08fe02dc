"""Fusion speed: per-frame latency of LandingFuser.update on an analytic scene (ARCHITECTURE.md §6, §9).

    python -m edge_landing.benchmarks.bench_fusion --frames 300 --altitude 40 --mode ned

The scene is ground plus a field of boxes (buildings), rendered by exact ray casting at the input size and
fed as metric depth with one-hot HVO, the way the network's outputs reach fusion. Each frame moves the
vehicle a little (and so the grid, in NED mode). Prints one JSON object: latency p50/p90/p99 in ms after
warm-up, frames per second, valid-target share, the thread's CPU time per frame (p50/p99: what the frame
costs, less inflated by other processes than wall time) and the machine's load average, because on a
shared machine a loaded CPU inflates every wall-clock figure. Thread pools as edge-run sets them: OpenCV at
``--opencv-threads`` (1; the distance transform alone takes twice as long on one thread), BLAS at 1.
There is no camera image, so motion geometry never runs and no spot is confirmed (valid share 0): this times
the network's grid and spot proposal only.
Fusion with geometry confirmation, on a rendered flight: ``benchmarks.bench_motion`` (frames without a stage run).
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from edge_landing.cli.common import CliParser, check_number, check_seed, check_threads, run_cli
from edge_landing.runtime.core.camera import (
    Attitude,
    Intrinsics,
    Mount,
    ned_from_camera,
)
from edge_landing.runtime.core.cpu_features import cpu_features
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import Prediction, VehicleState
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
from edge_landing.runtime.pipeline.threads import SideThreads, limit_side_threads


@dataclass(frozen=True)
class BenchConfig:
    frames: int = 300
    warmup: int = 20
    altitude_m: float = 40.0
    input_hw: tuple = (240, 320)
    working_hw: tuple = (120, 160)
    mode: str = "ned"              # "ned" (telemetry with position) or "vehicle" (no position)
    speed_mps: float = 5.0
    fps: float = 10.0
    seed: int = 0


def render_boxes(intr: Intrinsics, mount: Mount, attitude: Attitude, position_ned: np.ndarray,
                 boxes: np.ndarray) -> tuple:
    """Planar depth and HVO labels of ground (down = 0) plus axis-aligned boxes (K×2×3 min/max corners)."""
    d = intr.pixel_rays().astype(np.float64) @ ned_from_camera(mount, attitude).T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d[..., 2] > 0, -position_ned[2] / d[..., 2], np.inf)
        label = np.zeros(t.shape, dtype=np.uint8)
        for lo, hi in boxes:
            t1, t2 = (lo - position_ned) / d, (hi - position_ned) / d
            tmin = np.minimum(t1, t2)
            near, far = np.nanmax(tmin, axis=-1), np.nanmin(np.maximum(t1, t2), axis=-1)
            hit = (near <= far) & (near > 0) & (near < t)
            t = np.where(hit, near, t)
            top = np.nanargmax(tmin, axis=-1) == 2        # entered through the roof: horizontal
            label = np.where(hit, np.where(top, 0, 1), label).astype(np.uint8)
    depth = np.where(np.isfinite(t), t, np.nan).astype(np.float32)
    probs = np.zeros(depth.shape + (3,), dtype=np.float32)
    for k in range(3):
        probs[..., k] = (label == k) & np.isfinite(depth)
    return depth, probs


def scene(cfg: BenchConfig, n_poses: int = 8) -> tuple[Intrinsics, Mount, list, list]:
    """The camera, and ``n_poses`` pre-rendered frames ((depth, HVO) and (attitude, NED position)) over the box
    field, so that a timing loop times fusion alone."""
    rng = np.random.default_rng(cfg.seed)
    intr = Intrinsics.from_hfov(cfg.input_hw[1], cfg.input_hw[0])
    mount = Mount()
    centres = rng.uniform([-10, -60, 0], [150, 60, 0], size=(60, 3))
    sizes = rng.uniform([4, 4, 3], [15, 15, 25], size=(60, 3))
    boxes = np.stack([centres - sizes * [0.5, 0.5, 0] - [0, 0, 1] * sizes, centres + sizes * [0.5, 0.5, 0]], axis=1)
    preds, states = [], []
    for i in range(n_poses):
        pos = np.array([i * cfg.speed_mps / cfg.fps, 0.0, -cfg.altitude_m])
        att = Attitude(0.02 * math.sin(i), 0.03 * math.cos(i), 0.1 * i)
        preds.append(render_boxes(intr, mount, att, pos, boxes))
        states.append((att, pos))
    return intr, mount, preds, states


def run(cfg: BenchConfig) -> dict:
    if cfg.mode not in ("ned", "vehicle"):
        raise InputError(f"--mode must be 'ned' or 'vehicle', got '{cfg.mode}'")
    if cfg.frames < 10 or cfg.warmup < 0:
        raise InputError(f"--frames must be >= 10 and --warmup >= 0, got {cfg.frames} and {cfg.warmup}")
    intr, mount, preds, states = scene(cfg)
    fuser = LandingFuser(FusionConfig(working_hw=tuple(cfg.working_hw)), intr, mount)
    n_poses = len(preds)
    latencies, cpu_times, valid = [], [], 0
    for i in range(cfg.warmup + cfg.frames):
        t_s = i / cfg.fps
        depth, probs = preds[i % n_poses]
        att, pos = states[i % n_poses]
        state = VehicleState(t_s, att, pos if cfg.mode == "ned" else None)
        pred = Prediction(i, t_s, depth, probs)
        c0, t0 = time.thread_time(), time.perf_counter()
        target = fuser.update(pred, state, now_s=t_s)
        dt, dc = time.perf_counter() - t0, time.thread_time() - c0
        if i >= cfg.warmup:
            latencies.append(dt)
            cpu_times.append(dc)
            valid += bool(target.valid)
    lat_ms = np.array(latencies) * 1e3
    cpu_ms = np.array(cpu_times) * 1e3
    return {
        "benchmark": "fusion", "mode": cfg.mode, "altitude_m": cfg.altitude_m,
        "input_hw": list(cfg.input_hw), "working_hw": list(cfg.working_hw), "frames": cfg.frames,
        "warmup": cfg.warmup, "p50_ms": round(float(np.percentile(lat_ms, 50)), 3),
        "p90_ms": round(float(np.percentile(lat_ms, 90)), 3), "p99_ms": round(float(np.percentile(lat_ms, 99)), 3),
        "max_ms": round(float(lat_ms.max()), 3), "fps": round(1e3 / float(np.mean(lat_ms)), 1),
        "cpu_p50_ms": round(float(np.percentile(cpu_ms, 50)), 3),
        "cpu_p99_ms": round(float(np.percentile(cpu_ms, 99)), 3),
        "valid_share": round(valid / cfg.frames, 3), "loadavg_1m": round(os.getloadavg()[0], 2),
        "cpu_count": os.cpu_count(),
    }


def _main(argv: Sequence[str] | None = None) -> int:
    d = BenchConfig()
    ap = CliParser(prog="bench_fusion", description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=d.frames)
    ap.add_argument("--warmup", type=int, default=d.warmup)
    ap.add_argument("--altitude", type=float, default=d.altitude_m, help="metres above ground")
    ap.add_argument("--input", type=int, nargs=2, default=d.input_hw, metavar=("H", "W"))
    ap.add_argument("--working", type=int, nargs=2, default=d.working_hw, metavar=("H", "W"))
    ap.add_argument("--mode", default=d.mode, choices=("ned", "vehicle"))
    ap.add_argument("--seed", type=int, default=d.seed)
    ap.add_argument("--opencv-threads", type=int, default=1, help="OpenCV threads (edge-run uses 1)")
    a = ap.parse_args(argv)
    check_threads("--opencv-threads", a.opencv_threads)
    check_number("--altitude", a.altitude, 0.0, 1000.0, lo_open=True, unit="metres")
    check_seed("--seed", a.seed)
    for flag, (h, w) in (("--input", a.input), ("--working", a.working)):
        if not (16 <= h <= 4096 and 16 <= w <= 4096):
            raise InputError(f"{flag} must be two sizes between 16 and 4096 pixels (H W), got {h} {w}")
    cfg = BenchConfig(frames=a.frames, warmup=a.warmup, altitude_m=a.altitude, input_hw=tuple(a.input),
                      working_hw=tuple(a.working), mode=a.mode, seed=a.seed)
    limit_side_threads(SideThreads(opencv=a.opencv_threads, blas=1))     # as edge-run sets them
    result = run(cfg)
    result.update(opencv_threads=a.opencv_threads, cpu=cpu_features().summary())
    print(json.dumps(result))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
