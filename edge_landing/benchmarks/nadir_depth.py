"""Has the depth net learned one camera pose? Nadir views over flat ground, top third vs bottom third.

Looking straight down at level ground every pixel is (nearly) the same distance away, so the median depth of
the image's top third over that of its bottom third is ~1 in truth. A net that learned the 45° prior keeps
predicting the top as farther. For each style, views are rendered with the camera 90° down (clear air, fixed
sun) above the world's open landing spots, kept only when the truth is flat (≥ 97 % horizontal labels,
truth ratio within 3 % of 1); the error is predicted ratio / true ratio − 1 (scale-free: no calibration
needed). Goal (issue 14): |error| ≤ 0.10.

    python -m edge_landing.benchmarks.nadir_depth --model edge_landing/runtime/models/edgenet.onnx --out out/nadir.json
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from edge_landing.cli.common import CliParser, check_outputs_spare_inputs, check_seed, output_file, run_cli
from edge_landing.runtime.core.errors import ContractError, InputError

GOAL_MAX_ERROR = 0.10
MODELS = Path(__file__).resolve().parents[1] / "runtime" / "models"


@dataclass(frozen=True)
class NadirConfig:
    model: str
    styles: tuple[str, ...] = ("suburban", "urban", "rural")
    seed: int = 905
    heights_m: tuple[float, ...] = (20.0, 40.0, 80.0)
    views_per_height: int = 2
    width: int = 320
    height: int = 240


def thirds_ratio(depth_m: np.ndarray) -> float:
    """median depth of the top third / median depth of the bottom third (finite, positive pixels)."""
    h = depth_m.shape[0]
    top, bottom = depth_m[: h // 3], depth_m[h - h // 3:]

    def med(a: np.ndarray) -> float:
        a = a[np.isfinite(a) & (a > 0)]
        return float(np.median(a)) if a.size else math.nan

    return med(top) / med(bottom)


def nadir_views(cfg: NadirConfig, style: str) -> list[dict]:
    from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount
    from edge_landing.runtime.perception.inference import OnnxModel
    from edge_landing.sim.effects import Effects
    from edge_landing.sim.render import Renderer
    from edge_landing.sim.world import build_world

    world = build_world(style, cfg.seed)
    mount = Mount()
    intr = Intrinsics.from_hfov(cfg.width, cfg.height, math.radians(90.0))
    renderer = Renderer(world, intr, mount)
    model = OnnxModel.load(cfg.model, threads=1)
    rng = np.random.default_rng([cfg.seed, 77])
    rows: list[dict] = []
    spots = world.landing_spots[rng.permutation(len(world.landing_spots))]
    for height_m in cfg.heights_m:
        found = 0
        for n, e in spots:
            if found >= cfg.views_per_height:
                break
            if abs(n) > 300 or abs(e) > 300:
                continue
            ground = float(world.surface_z(np.array([n]), np.array([e]))[0])
            att = Attitude(0.0, -math.pi / 2 - mount.pitch_rad, float(rng.uniform(-math.pi, math.pi)))
            r = renderer.render(np.array([n, e, ground - height_m]), att, Effects(noise_sigma=0.005), rng)
            g = r.geometry
            labelled = g.hvo[g.hvo != 255]
            truth = thirds_ratio(g.depth_m)
            if labelled.size == 0 or np.mean(labelled == 0) < 0.97 or not abs(truth - 1.0) <= 0.03:
                continue
            pred = model.predict(r.rgb, out_hw=g.depth_m.shape)
            assert pred.depth_m is not None
            ratio = thirds_ratio(pred.depth_m)
            rows.append({"style": style, "height_m": height_m, "north_m": float(n), "east_m": float(e),
                         "truth_ratio": truth, "pred_ratio": ratio, "error": ratio / truth - 1.0})
            found += 1
    return rows


def run(cfg: NadirConfig) -> dict:
    rows = [r for s in cfg.styles for r in nadir_views(cfg, s)]
    errors = np.array([r["error"] for r in rows])
    return {"model": cfg.model, "views": rows, "mean_abs_error": float(np.mean(np.abs(errors))) if rows else None,
            "max_abs_error": float(np.max(np.abs(errors))) if rows else None, "goal_max_abs_error": GOAL_MAX_ERROR,
            "meets_goal": bool(rows) and bool(np.all(np.abs(errors) <= GOAL_MAX_ERROR))}


def _main(argv: Optional[Sequence[str]] = None) -> int:
    p = CliParser(prog="nadir_depth", description=__doc__.split("\n\n")[0])
    p.add_argument("--model", default=str(MODELS / "edgenet.onnx"))
    p.add_argument("--seed", type=int, default=905)
    p.add_argument("--out", help="write the figures to this JSON file")
    args = p.parse_args(argv)
    check_seed("--seed", args.seed)
    from edge_landing.runtime.perception.inference import read_contract

    try:
        read_contract(args.model)        # a missing or broken model: one line now, not after the first render
    except ContractError as exc:
        raise InputError(f"--model: {exc}") from None
    check_outputs_spare_inputs({"--out": args.out}, {"--model": args.model})
    out = output_file(args.out, "the --out file") if args.out else None
    result = run(NadirConfig(model=args.model, seed=args.seed))
    for r in result["views"]:
        print(f"{r['style']:9s} {r['height_m']:5.0f} m  truth top/bottom {r['truth_ratio']:.3f}  "
              f"predicted {r['pred_ratio']:.3f}  error {r['error']:+.3f}")
    print(f"mean |error| {result['mean_abs_error']:.3f}, max {result['max_abs_error']:.3f} "
          f"(goal <= {GOAL_MAX_ERROR}); {len(result['views'])} views")
    if out is not None:
        out.write_text(json.dumps(result, indent=1))
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
