"""Can a lying network land the drone on a car? Replays synthetic flights through fusion (ARCHITECTURE.md §11).

For each frame of an ``edge-sim --flight`` flight (rendered on the fly, poses as telemetry):
- ``lying``: a "model" that claims everything is flat horizontal ground: depth = the depth of the horizontal
  plane at the telemetry height above ground, HVO = horizontal everywhere;
- ``shipped``: the shipped EdgeNet with the in-flight altitude scale, as edge-run runs it.
Each is fused twice: with motion geometry (the default: only geometry-confirmed spots are sent) and without
it (the network's spot is sent, as before geometry existed). ``sent`` is what edge-run sends with telemetry:
the geometry-confirmed targets through the continuity of ARCHITECTURE.md §12 (a committed spot is re-sent
from memory on frames without a fresh confirmation). ``network_sent`` is the network alone as edge-run
``--allow-unconfirmed`` sends it, through the same continuity with its spots committed: what a target count
"as before geometry" compares with (the raw ``network`` count includes spots the continuity never sends, such
as those beyond its 2:1 cone). Every sent target is judged by ray casting
against the world (benchmarks/landing_truth.check_target). Also: motion geometry alone, per cell, against
the world's heights (recall of obstacles >= 1 m among cells it measured to <= 1 m, at 30-60 m AGL).

``--people`` adds people standing around the landing spots (sim.hazards.people_part; edge-sim --people too).
``--approach arc`` bends the approach sideways so that the direction of flight turns (sim.flight.Approach).
``--no-position`` replays telemetry with attitude and height above ground but no position: geometry then runs
on the image-only pose (fusion.image_motion); targets are judged where they point from the true pose.
``--pose-errors typical|harsh`` adds an autopilot's estimation errors to the telemetry fusion sees
(benchmarks.pose_errors); targets are judged where the autopilot would take them, relative to where it
believes it is.

    python -m edge_landing.benchmarks.lying_model --style urban --seed 41 --frames 200 --models lying shipped
"""
from __future__ import annotations

import argparse
import json
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from edge_landing.benchmarks.pose_errors import NoisyTelemetry, PoseErrorConfig, PoseErrors
from edge_landing.cli.common import (
    CliParser,
    check_choice,
    check_number,
    check_outputs_spare_inputs,
    check_seed,
    output_file,
    run_cli,
)
from edge_landing.runtime.core.camera import Intrinsics, Mount, ned_from_camera
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import Prediction, VehicleState
from edge_landing.runtime.fusion.deferred import StageTiming
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
from edge_landing.runtime.io.sources import SimReader


@dataclass(frozen=True)
class ReplayConfig:
    style: str = "suburban"
    seed: int = 41
    frames: int = 200
    fps: float = 10.0
    models: tuple[str, ...] = ("lying",)
    obstacle_height_m: float = 0.5
    recall_every: int = 10            # frames between per-cell geometry checks
    hazards: bool = True              # hazard-rich worlds (sim.hazards)
    people: bool = False              # people standing around the spots too (sim.hazards.people_part)
    approach: str = "straight"        # the flight's approach (sim.flight.Approach)
    width: int = SimReader.DEFAULT_SIZE[0]   # camera size (edge-run's sim camera's): the networks see it resized,
    height: int = SimReader.DEFAULT_SIZE[1]  # motion geometry crops it
    trace: str = ""                   # JSON lines, one per frame and model: why a target was (not) sent
    no_position: bool = False         # telemetry without position: geometry from the image-only pose
    pose_errors: PoseErrorConfig = PoseErrorConfig()   # an autopilot's estimation errors on what fusion sees
    geometry_timing: StageTiming = StageTiming.OVERLAPPED   # as edge-run runs the motion stage (fusion.deferred)


def lying_prediction(intr: Intrinsics, mount: Mount, state: VehicleState, frame_id: int) -> Prediction:
    """Flat horizontal ground everywhere: planar depth of the plane ``agl_m`` below, P(horizontal) = 1."""
    rays = intr.pixel_rays().reshape(-1, 3).astype(np.float64)
    down_cam = ned_from_camera(mount, state.attitude).T @ np.array([0.0, 0.0, 1.0])
    nx = rays @ down_cam
    with np.errstate(divide="ignore"):
        depth = np.where(nx > 1e-6, float(state.agl_m or 0.0) / nx, np.nan).reshape(intr.height, intr.width)
    hvo = np.zeros((intr.height, intr.width, 3), np.float32)
    hvo[..., 0] = 1.0
    return Prediction(frame_id, state.time_s, depth.astype(np.float32), hvo)


class _Shipped:
    def __init__(self, intr: Intrinsics, mount: Mount):
        from edge_landing.runtime.models import default_model_path
        from edge_landing.runtime.perception.inference import OnnxModel
        from edge_landing.runtime.perception.scale import AltitudeScaleEstimator
        from edge_landing.runtime.pipeline import ScaleStage

        self.model = OnnxModel.load(default_model_path(), 2)
        self.scale = ScaleStage(None, AltitudeScaleEstimator(), intr, mount)

    def __call__(self, rgb: np.ndarray, state: VehicleState, frame_id: int) -> Prediction:
        return self.scale.apply(self.model.predict(rgb, frame_id, state.time_s), state)


def cell_recall(world: Any, fuser: LandingFuser, agl_m: float, min_height_m: float = 1.0, open_radius_m: float = 1.5,
                origin_ne_m: tuple[float, float] = (0.0, 0.0)) -> Optional[tuple[int, ...]]:
    """Geometry alone, per cell, at 30-60 m AGL: among the cells of the fusion grid it measured to
    ``min_height_m`` or better within its memory (detectable height <= 1 m): (obstacle cells (world height >=
    1 m at the cell centre), of them marked obstacle, flat cells (< 0.05 m), of them marked, open flat cells
    (nothing >= 0.05 m within ``open_radius_m``: beyond the 1 m growth around obstacles), of them marked,
    obstacle cells at a step (something at least ``min_height_m`` lower within ``open_radius_m``: cars, trees,
    walls, roof edges; not the middle of a wide roof, which is a flat surface with no step in sight), of them
    marked)."""
    geo, view = fuser.geometry, fuser.grid
    if geo is None or view is None or not 30.0 <= agl_m <= 60.0:
        return None
    measured = np.isfinite(geo.detectable_m) & (geo.detectable_m <= min_height_m)
    if not measured.any():
        return (0,) * 8
    rows, cols = np.nonzero(measured)
    north = origin_ne_m[0] + view.north0_m + (rows + 0.5) * view.cell_m   # origin: the vehicle, without position
    east = origin_ne_m[1] + view.east0_m + (cols + 0.5) * view.cell_m

    def height(n: np.ndarray, e: np.ndarray) -> np.ndarray:
        out: np.ndarray = world.terrain.z_at(n, e) - world.surface_z(n, e)
        return out

    h = height(north, east)
    tall, flat = h >= min_height_m, h < 0.05
    ring = np.linspace(0.0, 2.0 * np.pi, 12, endpoint=False)
    ring_h = np.array([height(north + r * np.cos(a), east + r * np.sin(a)) for a in ring
                       for r in (0.5 * open_radius_m, open_radius_m)])
    open_flat = flat & (ring_h.max(axis=0) < 0.05)
    at_step = tall & (h - ring_h.min(axis=0) >= min_height_m)
    marked = geo.obstacle[rows, cols]
    return (int(tall.sum()), int((marked & tall).sum()), int(flat.sum()), int((marked & flat).sum()),
            int(open_flat.sum()), int((marked & open_flat).sum()), int(at_step.sum()), int((marked & at_step).sum()))


def _approach(text: str) -> Any:
    from edge_landing.sim.flight import Approach  # the sim extra, which every replay needs

    return Approach.from_string(text)


def replay(cfg: ReplayConfig, progress: bool = False) -> dict[str, Any]:
    from edge_landing import sim
    from edge_landing.benchmarks.landing_truth import TruthConfig, check_target
    from edge_landing.sim.generate import SimConfig, frame_effects, render_sample, vehicle_samples

    scfg = SimConfig(out=Path("."), frames=cfg.frames, style=sim.Style.from_string(cfg.style), seed=cfg.seed,
                     flight=True, fps=cfg.fps, width=cfg.width, height=cfg.height,
                     approach=sim.Approach.from_string(cfg.approach))
    world = sim.build_world(scfg.style, cfg.seed, hazards=cfg.hazards, people=cfg.people)
    mount = Mount()
    intr = scfg.intrinsics
    renderer = sim.Renderer(world, intr, mount)
    fusion = FusionConfig(obstacle_height_m=cfg.obstacle_height_m, geometry_timing=cfg.geometry_timing)
    truth = TruthConfig(log="", clearance_m=fusion.required_clearance_m)
    from edge_landing.runtime.pipeline.trust import Continuity, ContinuityConfig

    runs: dict[str, Any] = {}
    for name in cfg.models:
        runs[name] = {"continuity": Continuity(),
                      "network_continuity": Continuity(ContinuityConfig(commit_unconfirmed=True)),
                      "geometry": LandingFuser(fusion, intr, mount),
                      "network": LandingFuser(replace(fusion, allow_unconfirmed=True), intr, mount),
                      "model": _Shipped(intr, mount) if name == "shipped" else None}
    stats: dict[str, Any] = {name: {kind: {"targets": 0, "safe": 0, "failures": []}
                                    for kind in ("geometry", "sent", "network", "network_sent")}
                             for name in cfg.models}
    recall = {name: [0] * 8 for name in cfg.models}
    geo_ms: list[float] = []
    trace = open(cfg.trace, "w") if cfg.trace else None
    n_app, n_hov = int(round(cfg.frames * 0.4)), int(round(cfg.frames * 0.2))   # sim.flight's phases
    reported = NoisyTelemetry(cfg.pose_errors)
    for k, s in enumerate(vehicle_samples(scfg, world)):
        r = render_sample(scfg, k, s, renderer)
        state = VehicleState(s.t_s, s.attitude, s.position_ned_m.copy(), s.agl_m, "sim")
        noisy = reported(state)
        seen = replace(noisy, position_ned_m=None) if cfg.no_position else noisy
        for name, run in runs.items():
            # the lying network's claim is exact flat ground; the shipped one's metric scale uses telemetry
            pred = lying_prediction(intr, mount, state, k) if run["model"] is None else run["model"](r.rgb, noisy, k)
            fused = run["geometry"].fuse(pred, seen, s.t_s, r.rgb)
            sent, _ = run["continuity"].step(fused.target, seen, fused.grid, True, fused.placement)
            alone = run["network"].fuse(pred, seen, s.t_s, None)
            alone_sent, _ = run["network_continuity"].step(alone.target, seen, alone.grid, True, alone.placement)
            outcomes = {"geometry": fused.target, "sent": sent, "network": alone.target, "network_sent": alone_sent}
            for kind, target in outcomes.items():
                if cfg.no_position and target.valid and target.position_body_frd_m is not None:
                    body = np.asarray(target.position_body_frd_m, np.float64)   # judged where it points
                    target = replace(target, position_ned_m=s.position_ned_m + s.attitude.ned_from_body() @ body)
                elif target.valid and target.position_ned_m is not None and noisy.position_ned_m is not None \
                        and noisy is not state:
                    # the autopilot flies to the target relative to where it believes it is
                    offset = np.asarray(target.position_ned_m, np.float64) - noisy.position_ned_m
                    target = replace(target, position_ned_m=s.position_ned_m + offset)
                fuser = run[{"sent": "geometry", "network_sent": "network"}.get(kind, kind)]
                if kind == "geometry" and "geometry" in target.timings_s:
                    geo_ms.append(1e3 * target.timings_s["geometry"])
                if target.valid and target.position_ned_m is not None:
                    st = stats[name][kind]
                    st["targets"] += 1
                    ok, why = check_target(world, float(target.position_ned_m[0]), float(target.position_ned_m[1]),
                                           truth)
                    st["safe"] += ok
                    if not ok:
                        st["failures"].append({"frame": k, "why": why,
                                               "ned_m": [round(float(v), 2) for v in target.position_ned_m[:2]]})
                if trace is not None and kind == "geometry":
                    trace.write(json.dumps(_trace_row(k, n_app, n_hov, name, s, target, fuser, outcomes)) + "\n")
            if k % cfg.recall_every == 0:
                origin = (float(s.position_ned_m[0]), float(s.position_ned_m[1])) if cfg.no_position else (0.0, 0.0)
                counts = cell_recall(world, run["geometry"], s.agl_m, origin_ne_m=origin)
                if counts is not None:
                    recall[name] = [a + b for a, b in zip(recall[name], counts)]
        if progress and k % 20 == 0:
            print(f"  frame {k}/{cfg.frames}", flush=True)
    if trace is not None:
        trace.close()
    return {"config": asdict(cfg), "frames": cfg.frames, "stats": stats, "recall": recall,
            "geometry_ms_p50": float(np.median(geo_ms)) if geo_ms else math.nan,
            "weather": frame_effects(scfg, 0).to_json()}   # one draw per flight, as scene.json records it


def weather_text(weather: dict[str, float]) -> str:
    """What motion geometry feels most of a flight's weather (sim.effects.Effects.to_json), in one line's worth:
    'rain 0.85, sensor noise 0.019, haze 0.0012/m, blur 0 px'."""
    return (f"rain {weather['rain']:.2f}, sensor noise {weather['noise_sigma']:.3f}, haze {weather['haze_per_m']:.4f}/m, "
            f"blur {weather['motion_blur_px']:g} px")


def _trace_row(k: int, n_app: int, n_hov: int, name: str, s: Any, target: Any, fuser: LandingFuser,
               outcomes: dict[str, Any]) -> dict[str, Any]:
    """One frame of one model, for diagnosis: phase, fusion's target or reason, whether continuity sent one and
    the network alone had one, what the motion stage measured."""
    res = fuser.stage_result
    row: dict[str, Any] = {
        "frame": k, "model": name, "phase": "approach" if k < n_app else "hover" if k < n_app + n_hov else "descent",
        "agl_m": round(float(s.agl_m), 1), "valid": bool(target.valid), "reason": target.reason,
        "evidence": target.evidence, "motion": fuser.stage_reason, "sent": bool(outcomes["sent"].valid),
        "network": bool(outcomes["network"].valid), "network_sent": bool(outcomes["network_sent"].valid)}
    if res is not None:
        det = res.detectable_m[np.isfinite(res.detectable_m)]
        row.update(baseline_m=round(res.baseline_m, 2), ref_age_s=round(res.reference_age_s, 2),
                   noise_px=round(res.flow_noise_px, 3), rain=round(res.rain_share, 4),
                   measurable=round(det.size / res.detectable_m.size, 3), plane_raised_m=round(res.plane_raised_m, 1),
                   det_p50_m=round(float(np.median(det)), 3) if det.size else None,
                   plane_m=None if fuser.motion.ground_down_m is None
                   else round(fuser.motion.ground_down_m - float(s.position_ned_m[2]), 1))
    return row


def _summary(result: dict[str, Any]) -> str:
    n = result["frames"]
    lines = []
    for name, kinds in result["stats"].items():
        for kind, st in kinds.items():
            share = st["safe"] / st["targets"] if st["targets"] else math.nan
            lines.append(f"{name:8s} {kind:9s} targets on {st['targets']}/{n} frames ({100 * st['targets'] / n:.0f} %), "
                         f"safe {st['safe']}/{st['targets']} ({100 * share:.1f} %)")
        tall, hit, flat, fa, op, fo, step, sh = result["recall"][name]
        lines.append(f"{name:8s} geometry cells (30-60 m AGL, measured to <= 1 m): obstacles >= 1 m marked "
                     f"{hit}/{tall} ({100 * hit / max(tall, 1):.1f} %), of them at a >= 1 m step within 1.5 m "
                     f"{sh}/{step} ({100 * sh / max(step, 1):.1f} %), flat cells marked {fa}/{flat} "
                     f"({100 * fa / max(flat, 1):.1f} %), open flat cells (nothing within 1.5 m) marked {fo}/{op} "
                     f"({100 * fo / max(op, 1):.1f} %)")
    lines.append(f"geometry stage p50 {result['geometry_ms_p50']:.2f} ms per frame (inside fusion)")
    if "weather" in result:
        lines.append(f"weather drawn for the flight: {weather_text(result['weather'])}")
    return "\n".join(lines)


def check_camera_size(size: Sequence[int]) -> None:
    """``--size W H``: the replay's camera, 16 to 4096 pixels each way."""
    if not all(16 <= v <= 4096 for v in size):
        raise InputError(f"--size must be two sizes between 16 and 4096 pixels (W H), got {size[0]} {size[1]}")


def _check_args(a: argparse.Namespace) -> None:
    """Every value and both outputs checked before the (long) replay starts."""
    from edge_landing.sim.world import Style

    check_choice("--style", Style.from_string, a.style)
    check_seed("--seed", a.seed)
    if a.frames < 1:
        raise InputError(f"--frames must be at least 1, got {a.frames}")
    check_camera_size(a.size)
    check_number("--obstacle-height", a.obstacle_height, 0.0, 10.0, lo_open=True, unit="metres")
    check_choice("--pose-errors", PoseErrors.from_string, a.pose_errors)
    check_choice("--approach", _approach, a.approach)
    check_seed("--error-seed", a.error_seed)
    check_outputs_spare_inputs({"--json": a.json, "--trace": a.trace}, {})
    if a.trace:
        output_file(a.trace, "the --trace file")
    if a.json:
        output_file(a.json, "the --json file")


def _main(argv: Optional[Sequence[str]] = None) -> int:
    p = CliParser(prog="lying_model", description=__doc__.split("\n\n")[0],
                  formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--style", default="suburban")
    p.add_argument("--seed", type=int, default=41)
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--models", nargs="+", default=["lying"], choices=["lying", "shipped"])
    p.add_argument("--obstacle-height", type=float, default=0.5)
    p.add_argument("--size", type=int, nargs=2, default=SimReader.DEFAULT_SIZE, metavar=("W", "H"),
                   help="camera size (default: edge-run's built-in sim camera's)")
    p.add_argument("--no-hazards", action="store_true", help="the plain towns (no sim.hazards)")
    p.add_argument("--people", action="store_true", help="people standing around the landing spots too: a pixel "
                   "or two wide at 640 px from 40 m, narrower than motion geometry resolves")
    p.add_argument("--approach", default="straight", help="the flight's approach: straight (default) or arc (bent "
                   "sideways, so the direction of flight turns; edge-sim --approach)")
    p.add_argument("--no-position", action="store_true", help="telemetry without position (image-only pose)")
    p.add_argument("--pose-errors", default="none", help="an autopilot's estimation errors added to the telemetry "
                   "fusion sees: none (the simulator's exact pose), typical or harsh (benchmarks.pose_errors)")
    p.add_argument("--error-seed", type=int, default=0, help="seed of the pose errors")
    p.add_argument("--json", help="write the result here")
    p.add_argument("--trace", default="", help="write one JSON line per frame and model (fusion's reason, whether a "
                   "target was sent and the network alone had one, motion figures)")
    p.add_argument("--geometry-timing", default="overlapped", help="overlapped (edge-run's default: a frame's "
                   "motion geometry reaches the next frame) or inline")
    a = p.parse_args(argv)
    _check_args(a)
    result = replay(ReplayConfig(a.style, a.seed, a.frames, models=tuple(a.models),
                                 obstacle_height_m=a.obstacle_height, width=a.size[0], height=a.size[1],
                                 hazards=not a.no_hazards, people=a.people, approach=a.approach, trace=a.trace,
                                 no_position=a.no_position,
                                 pose_errors=PoseErrors.from_string(a.pose_errors).config(a.error_seed),
                                 geometry_timing=StageTiming.from_string(a.geometry_timing)),
                    progress=True)
    print(f"{a.style} seed {a.seed}, {a.frames} frames, camera {a.size[0]}x{a.size[1]}"
          + (", people standing around the spots" if a.people else "")
          + (f", {a.approach} approach" if a.approach != "straight" else "")
          + (", telemetry without position" if a.no_position else "")
          + (f", {a.pose_errors} pose errors (seed {a.error_seed})" if a.pose_errors != "none" else "")
          + f", geometry {a.geometry_timing}")
    print(_summary(result))
    if a.json:
        Path(a.json).write_text(json.dumps(result, indent=1))
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
