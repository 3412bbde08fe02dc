"""``edge-sim OUT --frames N --style suburban|urban --seed S [...]``: render a synthetic benchmark scene."""
from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Optional, Sequence

from edge_landing.cli.common import CliParser, check_choice, run_cli
from edge_landing.runtime.core.errors import InputError

from .effects import EffectOverrides
from .flight import Approach
from .generate import SimConfig, generate
from .world import LabelRule, Style


def build_parser() -> argparse.ArgumentParser:
    p = CliParser(prog="edge-sim", description="Render an AirSimNC-style synthetic bird's-eye-view scene folder "
                  "(RGB, planar depth, HVO labels, normals, poses) by ray casting procedural worlds.",
                  extra="sim", extra_modules=("embreex", "tqdm"))   # trimesh: not imported by the generator
    p.add_argument("out", type=Path, help="scene folder to write")
    p.add_argument("--frames", type=int, default=10, help="number of frames (default 10)")
    p.add_argument("--style", default="suburban",
                   help="world style: suburban, urban or rural (rural = the held-out zero-shot style, "
                        "never for training; default suburban)")
    p.add_argument("--seed", type=int, default=0, help="world and frame seed (default 0)")
    p.add_argument("--height", type=int, default=240, help="image height in pixels (default 240)")
    p.add_argument("--width", type=int, default=320, help="image width in pixels (default 320)")
    p.add_argument("--hfov-deg", type=float, default=None,
                   help="horizontal field of view (default 90; with --randomise drawn per scene in 60-110)")
    p.add_argument("--randomise", action="store_true",
                   help="domain randomisation (opt-in, so existing seeds render as before): camera pitch 20-90 deg "
                        "down, height 10-120 m, HFOV 60-110 deg, roll/pitch jitter; per-scene material palette "
                        "and textures; per-frame white balance, vignetting, defocus, noise, JPEG (all recorded in "
                        "scene.json)")
    fx = p.add_argument_group("effects (random per frame unless given)")
    fx.add_argument("--sun-azimuth-deg", type=float, help="sun azimuth from north, degrees")
    fx.add_argument("--sun-elevation-deg", type=float, help="sun elevation above the horizon, 5-90 degrees")
    fx.add_argument("--visibility-m", type=float, help="meteorological visibility in metres (haze/fog)")
    fx.add_argument("--rain", type=float, help="rain strength 0-1")
    fx.add_argument("--motion-blur-px", type=float, help="motion blur streak length in pixels")
    fx.add_argument("--noise-sigma", type=float, help="sensor noise, fraction of full scale (e.g. 0.01)")
    fx.add_argument("--exposure-ev", type=float, help="exposure offset in stops")
    fx.add_argument("--clear", action="store_true", help="fix every effect not given to clean conditions "
                    "(clear air, no rain, blur or noise, exposure 0); the sun stays random unless given")
    p.add_argument("--hazards", action="store_true", help="cars, bushes, trees, low walls, poles and clutter "
                   "around the open landing spots (sim/hazards.py)")
    p.add_argument("--people", action="store_true", help="people standing around the open landing spots, 6 per "
                   "spot within 20 m (sim/hazards.py; recorded in scene.json for landing_truth)")
    p.add_argument("--labels", default="landing", help="HVO labels: landing (default: vegetation, vehicles, clutter, "
                   "people and water are 'other' whatever their slope) or geometry (from the surface normal alone, "
                   "as the paper's AirSimNC)")
    p.add_argument("--flight", action="store_true", help="render one landing flight (approach, hover, descent) "
                   "and flight.mp4 instead of random views")
    p.add_argument("--approach", default="straight", help="a flight's approach: straight (default) or arc (bent "
                   "25 m sideways, camera turned towards the spot, so the direction of flight turns by up to ~35 "
                   "deg; sim/flight.py)")
    p.add_argument("--fps", type=float, default=10.0, help="frame rate for frame times and the video (default 10)")
    p.add_argument("--preview", action="store_true", help="write preview.png: RGB | depth | HVO per row")
    p.add_argument("--no-normals", action="store_true", help="do not write normals/*.npy")
    p.add_argument("--shadow-stride", type=int, default=1, help="cast shadow rays every N pixels (faster, default 1)")
    p.add_argument("--overwrite", action="store_true", help="replace a scene already in OUT")
    p.add_no_progress()
    return p


def _overrides(args: argparse.Namespace) -> EffectOverrides:
    def check(name: str, value: Optional[float], lo: float, hi: float) -> Optional[float]:
        if value is not None and not (lo <= value <= hi and math.isfinite(value)):
            raise InputError(f"--{name} must be between {lo:g} and {hi:g}, got {value:g}")
        return value

    check("sun-azimuth-deg", args.sun_azimuth_deg, -360, 360)
    check("sun-elevation-deg", args.sun_elevation_deg, 5, 90)
    check("visibility-m", args.visibility_m, 10, 1e7)
    check("rain", args.rain, 0, 1)
    check("motion-blur-px", args.motion_blur_px, 0, 50)
    check("noise-sigma", args.noise_sigma, 0, 0.5)
    check("exposure-ev", args.exposure_ev, -4, 4)
    clear = args.clear

    def pick(value, clean):
        return value if value is not None else (clean if clear else None)

    return EffectOverrides(
        sun_azimuth_rad=None if args.sun_azimuth_deg is None else math.radians(args.sun_azimuth_deg),
        sun_elevation_rad=None if args.sun_elevation_deg is None else math.radians(args.sun_elevation_deg),
        haze_per_m=pick(None if args.visibility_m is None else 3.0 / args.visibility_m, 0.0002),
        rain=pick(args.rain, 0.0), motion_blur_px=pick(args.motion_blur_px, 0.0),
        noise_sigma=pick(args.noise_sigma, 0.0), exposure_ev=pick(args.exposure_ev, 0.0))


def config_from_args(argv: Optional[Sequence[str]]) -> tuple[SimConfig, bool]:
    """(configuration, no progress bar) from command-line arguments; bad values raise InputError."""
    args = build_parser().parse_args(argv)
    approach = check_choice("--approach", Approach.from_string, args.approach)
    labels = check_choice("--labels", LabelRule.from_string, args.labels)
    hfov_deg = args.hfov_deg
    if hfov_deg is None:
        from .randomise import scene_hfov_deg

        hfov_deg = scene_hfov_deg(args.seed) if args.randomise else 90.0
    return SimConfig(out=args.out, frames=args.frames, style=Style.from_string(args.style), seed=args.seed,
                     width=args.width, height=args.height, hfov_deg=hfov_deg, effects=_overrides(args),
                     randomise=args.randomise, hazards=args.hazards, people=args.people,
                     approach=approach, labels=labels, flight=args.flight, fps=args.fps, preview=args.preview,
                     write_normals=not args.no_normals, shadow_stride=args.shadow_stride,
                     overwrite=args.overwrite), args.no_progress


def _main(argv: Optional[Sequence[str]]) -> int:
    config, no_progress = config_from_args(argv)
    out = generate(config, progress=not no_progress)
    print(f"edge-sim: wrote {config.frames} {config.style} frame(s) to {out}")
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
