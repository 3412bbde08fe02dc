"""Are the landing targets as safe at the camera's real resolution as at 320×240? (issue 17, ARCHITECTURE.md §6, §9)

Flies the same world and path (``edge-sim --flight``) at several image sizes, replays each flight.mp4 with
its poses through the drone's chain (model -> altitude scale -> fusion in local NED, what ``edge-run
--camera flight.mp4 --poses poses.csv --sequential`` runs) and judges every target by ray casting
(benchmarks/landing_truth.py). It also scores the network per pixel against the render's own ground truth
(sampled every ``pixel_every`` frames): the share of pixels voted horizontal that are not (false_h) and the
median relative depth error after a per-frame median scale (abs_rel), which vary much less than the
target counts.

    python -m edge_landing.benchmarks.resolution_sweep --styles urban suburban --seeds 67 13 --frames 100

What it found (shipped EdgeNet, 200-frame flights, flight.mp4, sequential replay; see the issue's report):
at 640×480 the network is as good as or better than at 320×240 per pixel on every world tried (false_h and
abs_rel lower), and the safe share of targets moves both ways between sizes by single episodes (a kept spot
next to an obstacle that both sizes see at a clearance just under or over 2 m). A frame not of the model's
4:3 shape was squashed into 320×240 before; it is now letterboxed (runtime/perception/input_fit.py).
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np

from edge_landing.cli.common import run_cli
from edge_landing.runtime.core.errors import InputError

SIZES = ((320, 240), (640, 480), (1280, 720))


@dataclass(frozen=True)
class SweepConfig:
    out: Path                                   # render cache (one folder per style, seed, size, frames)
    styles: Tuple[str, ...] = ("urban", "suburban")
    seeds: Tuple[int, ...] = (67, 13)           # not in the shipped model's training worlds (edgenet.json)
    sizes: Tuple[Tuple[int, int], ...] = SIZES  # (width, height)
    frames: int = 100
    clearance_m: float = 2.0
    pixel_every: int = 5                        # per-pixel scores on every n-th frame (0: none)
    video: bool = True                          # replay flight.mp4 (the user's path); False: the lossless PNGs
    model: Optional[str] = None                 # default: the shipped model
    geometry: bool = True                       # motion geometry confirms spots, as edge-run does (§11);
                                                # False: every network spot counts (the network alone)


@dataclass
class FlightResult:
    style: str
    seed: int
    width: int
    height: int
    frames: int
    targets: int = 0
    safe: int = 0
    failures: List[Dict[str, Any]] = field(default_factory=list)
    false_h: float = math.nan
    abs_rel: float = math.nan
    sizes_line: str = ""

    @property
    def safe_share(self) -> float:
        return self.safe / self.targets if self.targets else math.nan


def render(style: str, seed: int, width: int, height: int, frames: int, out: Path) -> Path:
    """The edge-sim flight folder for these settings, rendered once and reused."""
    from edge_landing.sim.generate import SimConfig, generate
    from edge_landing.sim.world import Style

    folder = out / f"{style}{seed}_{width}x{height}_{frames}"
    if not (folder / "scene.json").is_file():
        generate(SimConfig(out=folder, frames=frames, style=Style.from_string(style), seed=seed, width=width,
                           height=height, flight=True, write_normals=False, overwrite=True), progress=False)
    return folder


def _frames(folder: Path, video: bool) -> Iterator[np.ndarray]:
    import cv2

    if video:
        cap = cv2.VideoCapture(str(folder / "flight.mp4"))
        try:
            while True:
                ok, bgr = cap.read()
                if not ok or bgr is None:
                    return
                yield cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        finally:
            cap.release()
    for p in sorted((folder / "rgb").glob("*.png")):
        image = cv2.imread(str(p))
        if image is not None:
            yield cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def _pixel_scores(pred: Any, folder: Path, index: int) -> Tuple[int, int, float]:
    """(pixels voted horizontal, of them not horizontal in truth, median abs rel after median scale)."""
    import cv2

    hvo_truth = cv2.imread(str(folder / "hvo" / f"{index:06d}.png"), cv2.IMREAD_UNCHANGED)
    if hvo_truth is None:
        return 0, 0, math.nan
    depth_truth = np.load(folder / "depth" / f"{index:06d}.npy")
    h, w = pred.depth_m.shape
    # The truth sampled at the prediction's pixel centres (nearest: labels must not blend).
    hvo_t = cv2.resize(hvo_truth, (w, h), interpolation=cv2.INTER_NEAREST)
    depth_t = cv2.resize(depth_truth, (w, h), interpolation=cv2.INTER_NEAREST)
    voted = (pred.hvo_prob[..., 0] > 0.5) & (hvo_t != 255)
    ok = np.isfinite(depth_t) & (depth_t > 0) & np.isfinite(pred.depth_m)
    s = float(np.median(depth_t[ok] / pred.depth_m[ok])) if ok.any() else math.nan
    rel = float(np.median(np.abs(pred.depth_m[ok] * s - depth_t[ok]) / depth_t[ok])) if ok.any() else math.nan
    return int(voted.sum()), int((voted & (hvo_t != 0)).sum()), rel


def fly(config: SweepConfig, style: str, seed: int, width: int, height: int, model: Any = None,
        world: Any = None) -> FlightResult:
    """Render (or reuse) one flight at one size, replay it through the runtime chain, judge its targets."""
    from edge_landing.benchmarks.landing_truth import TruthConfig, check_target
    from edge_landing.runtime.core.camera import Intrinsics, Mount
    from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
    from edge_landing.runtime.io.replay import PoseReplayReader
    from edge_landing.runtime.models import default_model_path
    from edge_landing.runtime.perception.inference import OnnxModel
    from edge_landing.runtime.perception.input_fit import describe_for_model
    from edge_landing.runtime.perception.scale import AltitudeScaleEstimator
    from edge_landing.runtime.pipeline import ScaleStage
    from edge_landing.runtime.pipeline.trust import Continuity, ContinuityConfig

    folder = render(style, seed, width, height, config.frames, Path(config.out))
    model = model or OnnxModel.load(config.model or default_model_path(), threads=2)
    if world is None:
        from edge_landing import sim

        world = sim.build_world(style, seed)
    states = PoseReplayReader.states_from_csv(str(folder / "poses.csv"))
    intrinsics, mount = Intrinsics.from_hfov(width, height, math.radians(90.0)), Mount()
    # With geometry the frame goes to fusion as edge-run gives it (motion geometry works on the camera frame at
    # its own size) and the trust rules' continuity re-sends committed spots, as edge-run does; without, the
    # network's spots are taken unconfirmed, to compare the network across sizes.
    fusion_cfg = FusionConfig(vehicle_radius_m=config.clearance_m / 2, margin_m=config.clearance_m / 2,
                              allow_unconfirmed=not config.geometry)
    fuser = LandingFuser(fusion_cfg, intrinsics, mount)
    continuity = Continuity(ContinuityConfig(min_clearance_m=config.clearance_m)) if config.geometry else None
    scale = ScaleStage(None, AltitudeScaleEstimator(), intrinsics, mount)
    truth = TruthConfig("", style, seed, clearance_m=config.clearance_m)
    result = FlightResult(style, seed, width, height, 0)
    voted = wrong = 0
    rels = []
    for k, rgb in enumerate(_frames(folder, config.video)):
        if k >= len(states):
            break
        if k == 0:
            result.sizes_line = describe_for_model(model, rgb.shape[:2], fusion_cfg.working_hw)
        state = states[k]
        pred = model.predict(rgb, k, state.time_s)
        if config.pixel_every and k % config.pixel_every == 0 and pred.valid:
            v, w_, rel = _pixel_scores(pred, folder, k)
            voted, wrong = voted + v, wrong + w_
            rels.append(rel)
        fused = fuser.fuse(scale.apply(pred, state), state, state.time_s, rgb if config.geometry else None)
        target = fused.target
        if continuity is not None:  # what edge-run sends: a committed spot is re-sent from memory (§12)
            target, _ = continuity.step(target, state, fused.grid, reached_fusion=pred.valid)
        result.frames += 1
        if target.valid and target.position_ned_m is not None:
            ok, why = check_target(world, float(target.position_ned_m[0]), float(target.position_ned_m[1]), truth)
            result.targets += 1
            result.safe += ok
            if not ok:
                result.failures.append({"frame": k, "why": why})
    result.false_h = wrong / voted if voted else math.nan
    result.abs_rel = float(np.nanmean(rels)) if rels else math.nan
    return result


def sweep(config: SweepConfig, progress: Callable[[str], None] = print) -> List[FlightResult]:
    from edge_landing import sim
    from edge_landing.runtime.models import default_model_path
    from edge_landing.runtime.perception.inference import OnnxModel

    model = OnnxModel.load(config.model or default_model_path(), threads=2)
    results = []
    for style in config.styles:
        for seed in config.seeds:
            world = sim.build_world(style, seed)
            for width, height in config.sizes:
                t0 = time.monotonic()
                r = fly(config, style, seed, width, height, model, world)
                results.append(r)
                progress(f"{style} {seed} {width}x{height}: {r.safe}/{r.targets} safe, false_h {r.false_h:.4f}, "
                         f"abs_rel {r.abs_rel:.4f} ({time.monotonic() - t0:.0f} s)")
    return results


def table(results: Sequence[FlightResult]) -> str:
    rows = ["| style | seed | size | frames | targets | safe | safe share | false_h | abs_rel |",
            "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        rows.append(f"| {r.style} | {r.seed} | {r.width}×{r.height} | {r.frames} | {r.targets} | {r.safe} | "
                    f"{100 * r.safe_share:.1f} % | {r.false_h:.4f} | {r.abs_rel:.4f} |")
    rows += ["", "| size | targets | safe | safe share |", "|---|---|---|---|"]
    for width, height in dict.fromkeys((r.width, r.height) for r in results):
        sel = [r for r in results if (r.width, r.height) == (width, height)]
        t, s = sum(r.targets for r in sel), sum(r.safe for r in sel)
        rows.append(f"| {width}×{height} | {t} | {s} | {100 * s / t if t else math.nan:.1f} % |")
    return "\n".join(rows)


def parse_size(text: str) -> Tuple[int, int]:
    """``WIDTHxHEIGHT`` (as ``--sizes`` takes it) -> (width, height); InputError naming the bad value."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--sizes takes WIDTHxHEIGHT, got {text!r}") from None
    if not (16 <= w <= 4096 and 16 <= h <= 4096):
        raise InputError(f"--sizes {text}: width and height must be 16..4096 pixels")
    return w, h


def refuse_negative_sizes(argv: Optional[Sequence[str]]) -> None:
    """argparse takes ``--sizes -640x480``'s value for an option and says only "expected at least one argument":
    name the value instead (call before parsing)."""
    import re
    import sys

    for token in sys.argv[1:] if argv is None else argv:
        if re.fullmatch(r"-\d+x-?\d+", str(token), flags=re.IGNORECASE):
            parse_size(token)


def _main(argv: Optional[Sequence[str]] = None) -> int:
    from edge_landing.cli.common import CliParser, output_file, output_folder

    p = CliParser(prog="resolution_sweep", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="/tmp/edge_resolution_sweep", help="render cache folder")
    p.add_argument("--styles", nargs="+", default=["urban", "suburban"])
    p.add_argument("--seeds", nargs="+", type=int, default=[67, 13])
    p.add_argument("--sizes", nargs="+", default=[f"{w}x{h}" for w, h in SIZES])
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--png", action="store_true", help="replay the lossless PNGs instead of flight.mp4")
    p.add_argument("--network-only", action="store_true", help="count every network spot (no motion geometry), "
                   "to compare the network alone across sizes")
    p.add_argument("--json", help="also write the results here")
    refuse_negative_sizes(argv)
    a = p.parse_args(argv)
    if a.frames < 10:
        raise InputError(f"--frames must be at least 10 (a flight needs approach, hover and descent), got {a.frames}")
    for seed in a.seeds:
        if seed < 0:
            raise InputError(f"--seeds must be non-negative integers, got {seed}")
    from edge_landing.sim.world import Style

    for style in a.styles:
        try:
            Style.from_string(style)
        except InputError as exc:
            raise InputError(f"--styles: {exc}") from None
    config = SweepConfig(Path(a.out), tuple(a.styles), tuple(a.seeds), tuple(parse_size(s) for s in a.sizes),
                         a.frames, video=not a.png, geometry=not a.network_only)
    output_folder(a.out, "the --out folder")
    json_path = output_file(a.json, "the --json file") if a.json else None
    results = sweep(config)
    print(table(results))
    if json_path is not None:
        json_path.write_text(json.dumps([{**asdict(r), "safe_share": r.safe_share} for r in results], indent=1))
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
