"""Are edge-run's landing targets really safe? Checks a decision log against the synthetic world's geometry.

For every target in a ``--log targets.jsonl`` of ``edge-run --camera sim[:STYLE][:SEED]``, vertical rays are
cast every 5 cm (``--step``) over the disc of the requested clearance radius around the target's local NED
position. The target counts as safe when every ray hits a horizontal surface (normal within
``horizontal_max_deg`` of up, ARCHITECTURE.md §4), all hits lie within ``max_step_m`` of each other in height
(no kerb, car or wall inside), and none is water (level and "horizontal" by its normals, but no place to land).

The world (style, seed) comes from the log's first line, the ``{"run": {...}}`` header edge-run writes
(``sim_style``, ``sim_seed``; a sim camera's world has no hazards), or, for an ``edge-sim --flight`` video
replayed with its poses or its telemetry log, from the ``scene.json`` beside the video (style, seed and
whether hazards and people were rendered); ``--style``/``--seed``/``--hazards``/``--people`` override either.
A ``--camera sim-follow`` log's targets are in the autopilot's local NED: its home's place in the world
(``sim.follow.place_home``) is added. A log that names no world and no flags is refused: judging against the
wrong world gives a confident, wrong figure.

    edge-run --log /tmp/t.jsonl && python -m edge_landing.benchmarks.landing_truth /tmp/t.jsonl --clearance 2.0
"""
from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from edge_landing.cli.common import CliParser, check_choice, check_number, check_seed, run_cli
from edge_landing.runtime.core.errors import InputError


@dataclass(frozen=True)
class TruthConfig:
    log: str
    style: Optional[str] = None   # the world: None = from the log's run header (or the scene beside its video)
    seed: Optional[int] = None
    hazards: Optional[bool] = None   # sim.hazards in the world (edge-sim --hazards); None = from the same place
    people: Optional[bool] = None    # people around the spots (edge-sim --people); None = from the scene, else none
    clearance_m: float = 2.0      # the vehicle radius + margin edge-run was given (defaults 1 + 1)
    sample_step_m: float = 0.05   # rays every 5 cm: a 0.2 m post or a 0.24 m wall cannot fall between two
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
    from edge_landing.sim.world import Material  # the sim extra, loaded already: ``world`` is one of its worlds
    if (world.materials_at(prim, pts) == Material.WATER).any():
        return False, "water inside the disc"
    return True, "ok"


def read_log(path: str) -> tuple[Optional[dict[str, Any]], list[dict[str, Any]]]:
    """(run header or None, decision records) of an ``edge-run --log`` file."""
    try:
        with open(path) as f:
            lines = f.read().splitlines()
    except OSError as exc:
        raise InputError(f"cannot read decision log {path}: {exc.strerror}") from None
    records = []
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as exc:
            raise InputError(f"{path} line {number} is not JSON ({exc.msg}); expected edge-run --log lines") from None
    header = None
    if records and isinstance(records[0], dict) and isinstance(records[0].get("run"), dict):
        header, records = records[0]["run"], records[1:]
    return header, records


def scene_beside(header: Optional[dict[str, Any]]) -> tuple[dict[str, Any], str]:
    """The ``generator`` record of an edge-sim scene.json next to the log's video (and its path), or ({}, '')."""
    camera = (header or {}).get("camera")
    if (header or {}).get("source_kind") not in ("file", "folder") or not isinstance(camera, str):
        return {}, ""
    path = Path(camera).parent / "scene.json" if Path(camera).is_file() else Path(camera) / "scene.json"
    try:
        generator = json.loads(path.read_text()).get("generator") or {}
    except (OSError, ValueError, AttributeError):
        return {}, ""
    return (generator, str(path)) if isinstance(generator, dict) and generator.get("name") == "edge-sim" else ({}, "")


def world_of(cfg: TruthConfig, header: Optional[dict[str, Any]]) -> tuple[str, int, bool, bool, str]:
    """(style, seed, hazards, people, where they came from): the flags where given, the rest from the log's run
    header or from the edge-sim scene.json beside its video (a scene written before ``--people`` has none)."""
    run: dict[str, Any] = header or {}
    scene, scene_path = scene_beside(header)
    sim_camera = run.get("sim_style") is not None
    style = cfg.style if cfg.style is not None else run.get("sim_style", None) or scene.get("style")
    seed = cfg.seed if cfg.seed is not None else run.get("sim_seed") if sim_camera else scene.get("seed")
    if style is None or seed is None:
        missing = " and ".join(f for f, v in (("--style", style), ("--seed", seed)) if v is None)
        if header is None:
            raise InputError(f"{cfg.log} has no run header naming its world (an older edge-run --log?); "
                             f"give {missing} of the sim world it was flown in")
        raise InputError(f"{cfg.log} comes from camera '{run.get('camera')}' ({run.get('source_kind')}), not a "
                         f"known sim world; give {missing} if it was rendered by edge-sim")
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise InputError(f"{cfg.log}: sim_seed {seed!r} in the run header is not a non-negative integer")
    hazards = cfg.hazards
    if hazards is None:
        if scene and not sim_camera and "hazards" not in scene:
            raise InputError(f"{scene_path} does not say whether hazards were rendered (written before it did); "
                             f"give --hazards or --no-hazards")
        hazards = bool(scene.get("hazards", False)) if not sim_camera else False
    people = cfg.people if cfg.people is not None else bool(scene.get("people", False)) and not sim_camera
    flags = (("--style", cfg.style), ("--seed", cfg.seed), ("--hazards", cfg.hazards), ("--people", cfg.people))
    given = [f for f, v in flags if v is not None]
    where = f"{scene_path}" if scene and not sim_camera else "the log header"
    source = ("/".join(given) + (f" and {where}" if len(given) < len(flags) else "")) if given else where
    return str(style), seed, bool(hazards), bool(people), source


def evaluate(cfg: TruthConfig) -> dict:
    from edge_landing import sim

    header, records = read_log(cfg.log)
    if not records:
        raise InputError(f"{cfg.log} holds no decisions (expected the JSON lines of edge-run --log)")
    style, seed, hazards, people, source = world_of(cfg, header)
    targets = [r for r in records if r.get("valid") and r.get("ned_m")]
    world = sim.build_world(style, seed, hazards=hazards, people=people)
    # sim-follow: targets are in the autopilot's local NED, whose origin (home) sim.follow placed in the world
    offset = np.zeros(3)
    if (header or {}).get("source_kind") == "sim-follow":
        from edge_landing.sim.follow import place_home

        offset = place_home(world)
    failures = []
    for r in targets:
        ok, why = check_target(world, r["ned_m"][0] + offset[0], r["ned_m"][1] + offset[1], cfg)
        if not ok:
            failures.append({"frame": r["frame"], "ned_m": r["ned_m"], "why": why})
    safe = len(targets) - len(failures)
    return {"frames": len(records), "targets": len(targets), "safe": safe,
            "safe_share": safe / len(targets) if targets else math.nan, "failures": failures,
            "world": {"style": style, "seed": seed, "hazards": hazards, "people": people, "from": source},
            "config": cfg.__dict__}


def _main(argv: Optional[Sequence[str]] = None) -> int:
    p = CliParser(prog="landing_truth", description=__doc__.split("\n\n")[0],
                  formatter_class=argparse.RawDescriptionHelpFormatter, extra="sim", extra_modules=("embreex",))
    p.add_argument("log", help="decision log of edge-run --log (JSON lines, the run header first)")
    p.add_argument("--style", help="sim world style (default: the log header's sim_style)")
    p.add_argument("--seed", type=int, help="sim world seed (default: the log header's sim_seed)")
    p.add_argument("--hazards", action=argparse.BooleanOptionalAction, default=None, help="whether the world has "
                   "edge-sim's hazards (default: the scene.json beside the log's video says; a sim camera's has none)")
    p.add_argument("--people", action=argparse.BooleanOptionalAction, default=None, help="whether it has edge-sim's "
                   "people (default: as the scene.json says; none where it does not say)")
    p.add_argument("--clearance", type=float, default=2.0, help="requested clearance radius, metres")
    p.add_argument("--step", type=float, default=TruthConfig.sample_step_m, help="spacing of the vertical rays "
                   "over the disc, metres (default 0.05: nothing wider than that falls between two)")
    a = p.parse_args(argv)
    if a.seed is not None:
        check_seed("--seed", a.seed)
    if a.style is not None:
        from edge_landing.sim.world import Style

        check_choice("--style", Style.from_string, a.style)
    check_number("--clearance", a.clearance, 0.0, 50.0, lo_open=True, unit="metres")
    check_number("--step", a.step, 0.0, 1.0, lo_open=True, unit="metres")
    result = evaluate(TruthConfig(a.log, a.style, a.seed, a.hazards, a.people, a.clearance, sample_step_m=a.step))
    w = result["world"]
    print(f"{result['safe']}/{result['targets']} targets on ground-truth horizontal, level, dry ground with "
          f"{a.clearance:.1f} m clearance, rays every {a.step:.2f} m ({100 * result['safe_share']:.1f} %); "
          f"{result['frames']} frames; "
          f"world {w['style']} seed {w['seed']}{' with hazards' if w['hazards'] else ''}"
          f"{' and people' if w['people'] else ''} (from {w['from']})")
    for f in result["failures"][:10]:
        print(f"  frame {f['frame']}: {f['why']} at NED {[round(v, 1) for v in f['ned_m']]}")
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
