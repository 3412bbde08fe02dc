"""Can a lying network land the drone next to a person? Narrow obstacles against motion geometry (ARCHITECTURE.md §11).

A flat grass field holds boxes of one size on a square grid (by default people: 0.45 × 0.28 m, 1.7 m tall,
7 m apart, so that a clear 2 m disc fits between any four). The camera (640×480, 90°, 45° down) flies north
over it at each height with a gentle weave; every frame goes through fusion with the lying model (flat
horizontal ground everywhere, benchmarks.lying_model) and motion geometry, as edge-run fuses it with exact
telemetry. Every confirmed target is judged by ray casting (landing_truth.check_target): "unsafe" means a box
stands inside its clearance disc. Geometry is the only evidence against the boxes here, so the unsafe share is
what geometry misses where fusion's spots happened to be; what it said about every box, whatever the spots, is
counted too (``BoxCells``: boxes measured, confirmed clear on some frame, marked as obstacles). DIS reads an
object a few pixels wide at a fraction of its height (docs/MEASUREMENTS.md, "Narrow obstacles").

    python -m edge_landing.benchmarks.narrow_obstacles --heights 30 40 50 --box 0.45 0.28 1.7 --spacing 7
"""
from __future__ import annotations

import argparse
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from edge_landing.cli.common import CliParser, check_number, check_outputs_spare_inputs, output_file, run_cli
from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import VehicleState
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser

CLOTHING = (0.15, 0.18, 0.35)


@dataclass(frozen=True)
class FieldConfig:
    """Metres, frames; ``box`` = (along north, across, height) of every box."""

    heights_m: tuple[float, ...] = (30.0, 40.0, 50.0)
    box_m: tuple[float, float, float] = (0.45, 0.28, 1.7)
    spacing_m: float = 7.0
    frames: int = 60
    speed_mps: float = 10.0
    fps: float = 10.0
    width: int = 640
    height: int = 480
    seed: int = 1                      # the camera's sensor noise
    material: str = "clutter"          # sim.world.Material of the boxes' sides (tops: ``top``)
    top: str = "clutter"
    colour: tuple[float, float, float] = CLOTHING   # RGB albedo tint of the sides

    def __post_init__(self) -> None:
        for h in self.heights_m:
            check_number("--heights", h, 10.0, 120.0, unit="metres above ground")
        for v in self.box_m:
            check_number("--box", v, 0.05, 10.0, unit="metres")
        check_number("--spacing", self.spacing_m, max(self.box_m[:2]), 50.0, lo_open=True, unit="metres")
        check_number("--frames", self.frames, 2, 2000)
        for flag, v in (("--size W", self.width), ("--size H", self.height)):
            check_number(flag, v, 64, 4096, unit="pixels")
        from edge_landing.sim.world import Material

        for flag, name in (("--material", self.material), ("--top", self.top)):
            if name.upper() not in Material.__members__ or name.upper() in ("TERRAIN", "WATER"):
                raise InputError(f"{flag} must be a box material such as clutter, wall, concrete, car_paint or "
                                 f"foliage, got {name!r}")
        for v in self.colour:
            check_number("--colour", v, 0.0, 1.0, unit="(RGB albedo)")


def fly(cfg: FieldConfig, agl_m: float) -> dict[str, Any]:
    """One pass at ``agl_m``: confirmed targets, how many have a box inside their disc, and the first reasons."""
    from edge_landing import sim
    from edge_landing.benchmarks.landing_truth import TruthConfig, check_target
    from edge_landing.benchmarks.lying_model import lying_prediction
    from edge_landing.sim.fields import flat_field, quiet_effects
    from edge_landing.sim.world import Material

    along, across, tall = cfg.box_m
    rows = [[n, e, along / 2, across / 2, tall] for n in np.arange(10.0, 10.0 + cfg.frames * cfg.speed_mps / cfg.fps
                                                                     + 3 * agl_m, cfg.spacing_m)
            for e in np.arange(-3 * agl_m, 3 * agl_m + 1e-6, cfg.spacing_m)]
    world = flat_field(rows, side=Material[cfg.material.upper()], tint=cfg.colour, top=Material[cfg.top.upper()])
    intr, mount = Intrinsics.from_hfov(cfg.width, cfg.height), Mount()
    renderer = sim.Renderer(world, intr, mount)
    effects = quiet_effects()
    fusion = FusionConfig()
    fuser = LandingFuser(fusion, intr, mount)
    truth = TruthConfig(log="", clearance_m=fusion.required_clearance_m)
    rng = np.random.default_rng(cfg.seed)
    confirmed, unsafe, why = 0, 0, list[str]()
    seen = BoxCells(np.array([[r[0], r[1]] for r in rows]), fusion.obstacle_height_m)
    for k in range(cfg.frames):
        t_s = k / cfg.fps
        p = np.array([-10.0 + cfg.speed_mps * t_s, 2.0 * math.sin(0.1 * k), -agl_m])
        render = renderer.render(p, Attitude(), effects, rng)
        state = VehicleState(t_s, Attitude(), p, agl_m, "sim")
        target = fuser.update(lying_prediction(intr, mount, state, k), state, t_s, render.rgb)
        seen.add(fuser)
        if target.valid and target.position_ned_m is not None:
            confirmed += 1
            ok, reason = check_target(world, float(target.position_ned_m[0]), float(target.position_ned_m[1]), truth)
            unsafe += not ok
            if not ok and len(why) < 3:
                why.append(f"frame {k}: {reason}")
    return {"agl_m": agl_m, "frames": cfg.frames, "confirmed": confirmed, "unsafe": unsafe, "unsafe_examples": why,
            "boxes": seen.counts()}


class BoxCells:
    """What geometry alone said about each box, whatever spot fusion chose: the fusion-grid cell holding the box's
    centre, over a whole pass. Sent targets judge geometry only where a spot happened to be steered; this counts
    every box it measured (to the obstacle height), and how many of those it confirmed clear on some frame or
    marked as an obstacle."""

    def __init__(self, centres_ne_m: np.ndarray, obstacle_height_m: float):
        self.centres = centres_ne_m
        self.obstacle_height_m = obstacle_height_m
        self.measured = np.zeros(len(centres_ne_m), bool)
        self.clear = np.zeros(len(centres_ne_m), bool)
        self.obstacle = np.zeros(len(centres_ne_m), bool)

    def add(self, fuser: LandingFuser) -> None:
        geo, view = fuser.geometry, fuser.grid
        if geo is None or view is None:
            return
        for i, (north, east) in enumerate(self.centres):
            cell = view.cell_of(float(north), float(east))   # the geometry view is aligned with the grid
            if cell is not None:
                self.measured[i] |= bool(geo.detectable_m[cell] <= self.obstacle_height_m)
                self.clear[i] |= bool(geo.clear[cell])
                self.obstacle[i] |= bool(geo.obstacle[cell])

    def counts(self) -> dict[str, int]:
        return {"measured": int(self.measured.sum()), "confirmed_clear": int((self.measured & self.clear).sum()),
                "marked_obstacle": int((self.measured & self.obstacle).sum())}


def _main(argv: Optional[Sequence[str]] = None) -> int:
    p = CliParser(prog="narrow_obstacles", description=__doc__.split("\n\n")[0],
                  formatter_class=argparse.RawDescriptionHelpFormatter, extra="sim")
    p.add_argument("--heights", type=float, nargs="+", default=[30.0, 40.0, 50.0], help="metres above ground")
    p.add_argument("--box", type=float, nargs=3, default=[0.45, 0.28, 1.7], metavar=("ALONG", "ACROSS", "TALL"),
                   help="every box's size in metres (default: a standing person)")
    p.add_argument("--spacing", type=float, default=7.0, help="metres between boxes (a square grid)")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--material", default="clutter", help="the boxes' sides: clutter (textured, default), wall, "
                   "concrete, car_paint (nearly uniform), foliage ...")
    p.add_argument("--top", default="clutter", help="the boxes' tops (same choices)")
    p.add_argument("--colour", type=float, nargs=3, default=list(CLOTHING), metavar=("R", "G", "B"),
                   help="the sides' albedo tint, 0-1 (default dark blue clothing)")
    p.add_argument("--size", type=int, nargs=2, default=[640, 480], metavar=("W", "H"), help="camera pixels")
    p.add_argument("--json", help="write the results here")
    a = p.parse_args(argv)
    check_outputs_spare_inputs({"--json": a.json}, {})
    if a.json:
        output_file(a.json, "the --json file")
    cfg = FieldConfig(tuple(a.heights), tuple(a.box), a.spacing, a.frames, material=a.material, top=a.top,
                      colour=tuple(a.colour), width=a.size[0], height=a.size[1])
    print(f"boxes {cfg.box_m[0]:g} x {cfg.box_m[1]:g} m, {cfg.box_m[2]:g} m tall, {cfg.spacing_m:g} m apart, "
          f"{cfg.material} sides {tuple(cfg.colour)}, {cfg.top} tops; "
          f"camera {cfg.width}x{cfg.height}, lying model, {cfg.frames} frames per height", flush=True)
    results = []
    for agl in cfg.heights_m:
        r = fly(cfg, agl)
        results.append(r)
        b = r["boxes"]
        print(f"{agl:5.0f} m: {r['confirmed']} confirmed targets, {r['unsafe']} with a box inside the disc"
              + (f" (e.g. {r['unsafe_examples'][0]})" if r["unsafe_examples"] else "")
              + f"; geometry measured {b['measured']} boxes' cells, confirmed {b['confirmed_clear']} of them clear "
              f"on some frame, marked {b['marked_obstacle']} as obstacles", flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps({"config": asdict(cfg), "results": results}, indent=1))
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
