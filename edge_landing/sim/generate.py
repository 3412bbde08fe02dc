"""Scene generation: render N frames (random views or one landing flight) into a scene folder (ARCHITECTURE.md §4).

Every random draw comes from generators seeded by (seed, frame, purpose), so the same configuration gives
byte-identical files, and frame k does not depend on how many frames come before it.
"""
from __future__ import annotations

import logging
import math
import shutil
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterator, Optional

import numpy as np

from edge_landing.evaluation.scene import Pose, SceneMeta, SceneWriter
from edge_landing.runtime.core.camera import Intrinsics, Mount
from edge_landing.runtime.core.errors import InputError, SceneError
from edge_landing.runtime.core.geometry import HvoThresholds

from .effects import EffectOverrides, Effects, sample_effects
from .flight import (
    AGL_RANGE_M,
    PLAUSIBLE_SPEED_MPS,
    Approach,
    VehicleSample,
    peak_speed_mps,
    plan_flight,
    random_view,
)
from .render import Renderer, Rendering
from .world import WORLD_HALF_SIZE_M, LabelRule, Style, build_world

log = logging.getLogger(__name__)

SIM_VERSION = "1.0.0"
_PURPOSE_POSE, _PURPOSE_EFFECTS, _PURPOSE_SENSOR, _PURPOSE_FLIGHT = 1, 2, 3, 4
_PURPOSE_PALETTE, _PURPOSE_LOOK = 5, 6
SCENE_SUBFOLDERS = ("rgb", "depth", "hvo", "normals")


@dataclass(frozen=True)
class SimConfig:
    """What to generate. Sizes in pixels; ``fps`` sets frame times (t = frame / fps) and the video rate."""

    out: Path | str
    frames: int = 10
    style: Style = Style.SUBURBAN
    seed: int = 0
    width: int = 320
    height: int = 240
    hfov_deg: float = 90.0
    effects: EffectOverrides = field(default_factory=EffectOverrides)
    flight: bool = False
    fps: float = 10.0
    preview: bool = False
    write_normals: bool = True
    shadow_stride: int = 1
    overwrite: bool = False
    randomise: bool = False      # sim/randomise.py + sim/appearance.py: camera, palette and look draws
    hazards: bool = False       # sim.hazards around the landing spots
    people: bool = False        # people standing around them (sim.hazards.people_part)
    approach: Approach = Approach.STRAIGHT   # a flight's approach (sim.flight)
    labels: LabelRule = LabelRule.LANDING    # how HVO labels are made (sim.world.LabelRule)

    def __post_init__(self):
        if self.frames < 1:
            raise InputError(f"--frames must be at least 1, got {self.frames}")
        if self.seed < 0:  # numpy's SeedSequence takes non-negative integers only
            raise InputError(f"--seed must be a non-negative integer, got {self.seed}")
        for name in ("width", "height"):
            v = getattr(self, name)
            if not 16 <= v <= 4096:
                raise InputError(f"--{name} must be between 16 and 4096 pixels, got {v}")
        if not 10.0 <= self.hfov_deg <= 150.0:
            raise InputError(f"--hfov-deg must be between 10 and 150 degrees, got {self.hfov_deg}")
        if not 0.1 <= self.fps <= 240.0:
            raise InputError(f"--fps must be between 0.1 and 240, got {self.fps}")
        if not 1 <= self.shadow_stride <= 8:
            raise InputError(f"--shadow-stride must be between 1 and 8, got {self.shadow_stride}")
        if self.approach is not Approach.STRAIGHT and not self.flight:
            raise InputError(f"--approach {self.approach} needs --flight (random views have no approach)")

    @property
    def intrinsics(self) -> Intrinsics:
        return Intrinsics.from_hfov(self.width, self.height, math.radians(self.hfov_deg))


def frame_rng(seed: int, frame: int, purpose: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), int(frame), int(purpose)])


def pose_of(frame: int, s: VehicleSample) -> Pose:
    a = s.attitude
    n, e, d = (float(v) for v in s.position_ned_m)
    return Pose(int(frame), float(s.t_s), (n, e, d), float(a.roll_rad),
                float(a.pitch_rad), float(a.yaw_rad), float(s.agl_m))


def vehicle_samples(config: SimConfig, world) -> Iterator[VehicleSample]:
    """The vehicle pose of each frame, in order."""
    if config.flight:
        samples = plan_flight(world, frame_rng(config.seed, 0, _PURPOSE_FLIGHT), config.frames, config.fps,
                              config.approach)
        fastest = peak_speed_mps(samples)
        if fastest > PLAUSIBLE_SPEED_MPS:
            # The approach covers ~110 m whatever the frame count: a short flight is a fast one, and edge-run
            # (over 40 m/s) refuses its telemetry as position jumps.
            log.warning("this flight reaches %.0f m/s (%d frames at %g frames/s over a ~110 m approach), faster "
                        "than a multirotor flies; about %d frames or more keep it under %.0f m/s", fastest,
                        config.frames, config.fps, math.ceil(config.frames * fastest / PLAUSIBLE_SPEED_MPS),
                        PLAUSIBLE_SPEED_MPS)
        yield from samples
        return
    for k in range(config.frames):
        rng = frame_rng(config.seed, k, _PURPOSE_POSE)
        if config.randomise:
            from .randomise import randomised_view

            yield randomised_view(world, rng, t_s=k / config.fps)
        else:
            yield random_view(world, rng, t_s=k / config.fps)


def frame_effects(config: SimConfig, frame: int) -> Effects:
    """Per-frame draws for views; one draw for a whole flight (weather does not flicker), no blur unless asked."""
    if config.flight:
        fx = sample_effects(frame_rng(config.seed, 0, _PURPOSE_EFFECTS), config.effects)
        return fx if config.effects.motion_blur_px is not None else replace(fx, motion_blur_px=0.0)
    return sample_effects(frame_rng(config.seed, frame, _PURPOSE_EFFECTS), config.effects)


def _prepare_folder(config: SimConfig) -> None:
    out = Path(config.out)
    if out.exists() and not out.is_dir():
        raise InputError(f"output {out} exists and is not a folder; expected a new or empty scene folder")
    if out.is_dir():
        stale = [s for s in SCENE_SUBFOLDERS if (out / s).is_dir() and any((out / s).iterdir())]
        if stale and not config.overwrite:
            raise InputError(f"output {out} already holds a scene ({', '.join(stale)}/ not empty); "
                             f"pass --overwrite to replace it or choose a new folder")
        for s in stale:
            shutil.rmtree(out / s)
        for f in ("poses.csv", "scene.json", "flight.mp4", "flight.tlog", "preview.png"):
            if (out / f).exists() and config.overwrite:
                (out / f).unlink()


def generator_record(config: SimConfig, world, per_frame: list[dict]) -> dict:
    """Everything needed to regenerate the scene, for scene.json's ``generator``."""
    return {
        "name": "edge-sim", "version": SIM_VERSION, "style": str(config.style), "seed": int(config.seed),
        "hazards": bool(config.hazards), "people": bool(config.people), "labels": str(config.labels),
        "frames": int(config.frames), "mode": "flight" if config.flight else "views", "fps": float(config.fps),
        "width": config.width, "height": config.height, "hfov_deg": float(config.hfov_deg),
        "elevation_range_m": list(AGL_RANGE_M), "agl": "distance straight down to the first surface",
        "effects": config.effects.to_json(), "shadow_stride": config.shadow_stride,
        "world": {"half_size_m": WORLD_HALF_SIZE_M, "triangles": int(len(world.tris)), "frame": "local NED"},
        "per_frame_effects": per_frame,
        **({"approach": str(config.approach)} if config.flight else {}),
        **({"randomise": randomise_record(config)} if config.randomise else {}),
    }


def randomise_record(config: SimConfig) -> dict:
    """What --randomise drew for the scene (per-frame camera looks are in per_frame_effects[k]['look'])."""
    from .appearance import sample_palette
    from .randomise import RANGES

    return {"views": RANGES.to_json() if not config.flight else "flight plan (not randomised)",
            "hfov_deg": float(config.hfov_deg),
            "palette": sample_palette(frame_rng(config.seed, 0, _PURPOSE_PALETTE)).to_json()}


def generate(config: SimConfig, progress: bool = True) -> Path:
    """Render the scene folder described by ``config``; returns its path."""
    from tqdm import tqdm

    _prepare_folder(config)
    out = Path(config.out)
    thresholds = HvoThresholds()
    meta = SceneMeta(intrinsics=config.intrinsics, mount=Mount(), hvo_thresholds=thresholds)
    writer = SceneWriter(out, meta)            # fails fast on an unwritable folder, before the slow work
    world = build_world(config.style, config.seed, config.hazards, config.people)
    renderer = Renderer(world, config.intrinsics, meta.mount, thresholds, config.shadow_stride, config.labels)
    if config.randomise:
        from .appearance import sample_palette

        renderer.palette = sample_palette(frame_rng(config.seed, 0, _PURPOSE_PALETTE))
    video = _open_video(out / "flight.mp4", config) if config.flight else None
    per_frame, poses = [], []
    try:
        samples = vehicle_samples(config, world)
        for k, sample in enumerate(tqdm(samples, total=config.frames, desc=f"edge-sim {config.style}",
                                        unit="frame", disable=not progress)):
            fx = frame_effects(config, k)
            r = renderer.render(sample.position_ned_m, sample.attitude, fx, frame_rng(config.seed, k, _PURPOSE_SENSOR))
            g = r.geometry
            rgb, record = r.rgb, fx.to_json()
            if config.randomise:
                from .appearance import apply_look, sample_look

                look = sample_look(frame_rng(config.seed, k, _PURPOSE_LOOK))
                rgb, record["look"] = apply_look(rgb, look, frame_rng(config.seed, k, _PURPOSE_LOOK + 100)), look.to_json()
            poses.append(pose_of(k, sample))
            writer.write(k, rgb, g.depth_m, g.hvo, g.normals if config.write_normals else None, poses[-1])
            per_frame.append(record)
            if video is not None:
                import cv2

                video.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    finally:
        if video is not None:
            video.release()
        record = generator_record(config, world, per_frame)
        if video is not None and poses:   # the telemetry log a ground station would have kept (sim.tlog_writer)
            from .tlog_writer import write_flight_tlog

            record["tlog"] = write_flight_tlog(out / "flight.tlog", poses, config.seed)
        writer.meta = SceneMeta(meta.intrinsics, meta.mount, thresholds, generator=record)
        writer.close()
    if config.preview:
        from .preview import write_contact_sheet

        write_contact_sheet(out, out / "preview.png")
    return out


def _open_video(path: Path, config: SimConfig):
    import cv2

    video = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), float(config.fps),
                            (config.width, config.height))
    if not video.isOpened():
        raise SceneError(f"cannot open {path} for writing an mp4v video (OpenCV without an MP4 encoder?)")
    return video


def render_sample(config: SimConfig, frame: int, sample: VehicleSample,
                  renderer: Optional[Renderer] = None) -> Rendering:
    """Render one vehicle sample with the configuration's effects (used by the live camera and tests)."""
    if renderer is None:
        world = build_world(config.style, config.seed, config.hazards, config.people)
        renderer = Renderer(world, config.intrinsics, Mount(), HvoThresholds(), config.shadow_stride, config.labels)
    return renderer.render(sample.position_ned_m, sample.attitude, frame_effects(config, frame),
                           frame_rng(config.seed, frame, _PURPOSE_SENSOR))
