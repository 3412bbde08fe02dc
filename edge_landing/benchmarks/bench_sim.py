"""Speed of edge-sim: frames/s for random views at 240×320 on one core, after warm-up; prints JSON.

    python -m edge_landing.benchmarks.bench_sim [--style suburban] [--frames 30] [--shadow-stride 1]
"""
from __future__ import annotations

import json
import os
import time
from typing import Optional, Sequence

# One core: keep numpy's BLAS (and anything else threaded) to one thread before numpy loads.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

from edge_landing.cli.common import CliParser, check_choice, run_cli  # noqa: E402
from edge_landing.runtime.core.errors import InputError  # noqa: E402


def _main(argv: Optional[Sequence[str]] = None) -> int:
    p = CliParser(prog="bench_sim", description=__doc__.splitlines()[0], extra="sim", extra_modules=("embreex",))
    p.add_argument("--style", default="suburban")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--shadow-stride", type=int, default=1)
    p.add_argument("--any-core", action="store_true", help="do not pin the process to one CPU core")
    args = p.parse_args(argv)

    from edge_landing import sim
    from edge_landing.sim.generate import frame_effects, frame_rng

    style = check_choice("--style", sim.Style.from_string, args.style)
    if args.warmup < 0:
        raise InputError(f"--warmup must be >= 0, got {args.warmup}")
    # SimConfig checks --frames, --seed, --width, --height and --shadow-stride (one line naming the flag).
    config = sim.SimConfig(out=".", frames=args.frames, style=style, seed=args.seed,
                           width=args.width, height=args.height, shadow_stride=args.shadow_stride)
    if not args.any_core and hasattr(os, "sched_setaffinity"):
        # One core for real: Embree would otherwise build its BVH on every core.
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

    t0 = time.perf_counter()
    world = sim.build_world(style, args.seed)
    _ = world.scene                                     # Embree BVH build
    build_s = time.perf_counter() - t0
    renderer = sim.Renderer(world, config.intrinsics, shadow_stride=args.shadow_stride)
    times = []
    for k in range(args.warmup + args.frames):
        view = sim.random_view(world, frame_rng(args.seed, k, 1))
        fx = frame_effects(config, k)
        t = time.perf_counter()
        renderer.render(view.position_ned_m, view.attitude, fx, frame_rng(args.seed, k, 3))
        if k >= args.warmup:
            times.append(time.perf_counter() - t)
    ms = np.array(times) * 1000.0
    report = {
        "what": "edge-sim render (ray cast + shadows + shading + effects), random views",
        "style": args.style, "size": [args.height, args.width], "shadow_stride": args.shadow_stride,
        "threads": 1, "pinned_to_one_core": not args.any_core, "world_triangles": int(len(world.tris)),
        "world_build_s": round(build_s, 3),
        "frames": args.frames, "fps": round(1000.0 / float(np.mean(ms)), 2),
        "latency_ms": {"p50": round(float(np.percentile(ms, 50)), 1), "p90": round(float(np.percentile(ms, 90)), 1),
                       "mean": round(float(np.mean(ms)), 1)},
    }
    print(json.dumps(report, indent=2))
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
