"""Are edge-run's landing targets really safe? Checks a decision log against the synthetic world's geometry.

For every target in a ``--log targets.jsonl`` of ``edge-run --camera sim[:STYLE][:SEED]``, vertical rays are
cast over the disc of the requested clearance radius around the target's local NED position. The target
counts as safe when every ray hits a horizontal surface (normal within ``horizontal_max_deg`` of up,
ARCHITECTURE.md §4) and all hits lie within ``max_step_m`` of each other in height (no kerb, car or wall inside).

    edge-run --log /tmp/t.jsonl && python -m benchmarks.landing_truth /tmp/t.jsonl --clearance 2.0
"""
from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from edge_landing.cli.common import CliParser, run_cli
from edge_landing.runtime.core.errors import InputError


@dataclass(frozen=True)
class TruthConfig:
    log: str
    style: str = "suburban"
    seed: int = 0
    clearance_m: float = 2.0      # the vehicle radius + margin edge-run was given (defaults 1 + 1)
    sample_step_m: float = 0.25
    horizontal_max_deg: float = 10.0
    max_step_m: float = 0.3


def disc_offsets(radius_m: float, step_m: float) -> np.ndarray:
    g = np.arange(-radius_m, radius_m + 1e-9, step_m)
    n, e = np.meshgrid(g, g, indexing="ij")
    keep = n ** 2 + e ** 2 <= radius_m ** 2
    return np.stack([n[keep], e[keep]], axis=-1)


def check_target(world, north_m: float, east_m: float, cfg: TruthConfig) -> tuple:
    """(safe, why) for a target at (north, east) in the world's local NED frame."""
    pts = disc_offsets(cfg.clearance_m, cfg.sample_step_m) + np.array([north_m, east_m])
    origins = np.column_stack([pts, np.full(len(pts), -1000.0)])
    dirs = np.broadcast_to(np.array([0.0, 0.0, 1.0]), origins.shape)
    t, prim = world.intersect(origins, dirs)
    if (prim < 0).any():
        return False, "a ray missed the world"
    cos_up = np.abs(world.normals[prim][:, 2])
    tilt_deg = np.degrees(np.arccos(np.clip(cos_up, -1.0, 1.0)))
    if tilt_deg.max() > cfg.horizontal_max_deg:
        return False, f"surface tilted {tilt_deg.max():.0f}° inside the disc"
    heights = -1000.0 + t
    if np.ptp(heights) > cfg.max_step_m:
        return False, f"height step {np.ptp(heights):.2f} m inside the disc"
    return True, "ok"


def evaluate(cfg: TruthConfig) -> dict:
    from edge_landing import sim

    try:
        lines = open(cfg.log).read().splitlines()
    except OSError as exc:
        raise InputError(f"cannot read decision log {cfg.log}: {exc.strerror}") from None
    records = [json.loads(line) for line in lines if line.strip()]
    targets = [r for r in records if r.get("valid") and r.get("ned_m")]
    if not records:
        raise InputError(f"{cfg.log} holds no decisions (expected the JSON lines of edge-run --log)")
    world = sim.build_world(cfg.style, cfg.seed)
    failures = []
    for r in targets:
        ok, why = check_target(world, r["ned_m"][0], r["ned_m"][1], cfg)
        if not ok:
            failures.append({"frame": r["frame"], "ned_m": r["ned_m"], "why": why})
    safe = len(targets) - len(failures)
    return {"frames": len(records), "targets": len(targets), "safe": safe,
            "safe_share": safe / len(targets) if targets else math.nan, "failures": failures,
            "config": cfg.__dict__}


def _main(argv: Optional[Sequence[str]] = None) -> int:
    p = CliParser(prog="landing_truth", description=__doc__.split("\n\n")[0],
                  formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("log")
    p.add_argument("--style", default="suburban")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--clearance", type=float, default=2.0, help="requested clearance radius, metres")
    a = p.parse_args(argv)
    result = evaluate(TruthConfig(a.log, a.style, a.seed, a.clearance))
    print(f"{result['safe']}/{result['targets']} targets on ground-truth horizontal, level ground with "
          f"{a.clearance:.1f} m clearance ({100 * result['safe_share']:.1f} %); {result['frames']} frames")
    for f in result["failures"][:10]:
        print(f"  frame {f['frame']}: {f['why']} at NED {[round(v, 1) for v in f['ned_m']]}")
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
