"""``edge-run``: camera -> depth + HVO -> landing target -> MAVLink, on the drone (ARCHITECTURE.md §1, §6, §8).

    edge-run                                        # the built-in synthetic flight, shipped model, prints targets
    edge-run --camera /dev/video0 --mav udpout:127.0.0.1:14550 --autopilot ardupilot
    edge-run --camera flight.mp4 --model edgenet.onnx --precision fp32 --record overlay.mp4 --log targets.jsonl
    edge-run --camera flight.mp4 --tlog flight.tlog --tlog-video-start 2026-11-24T10:00:03.2Z --log targets.jsonl

Ctrl-C or SIGTERM (systemd stopping the service) stops cleanly: the summary is printed and every file is flushed.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Optional, Sequence, TextIO

from edge_landing import __version__
from edge_landing.cli.common import (
    CliParser,
    check_number,
    check_outputs_spare_inputs,
    check_threads,
    output_file,
    run_cli,
)
from edge_landing.cli.run_camera import (
    add_camera_arguments,
    camera_geometry,
    check_camera_flags,
    check_gimbal,
    check_tlog,
    recorded_source,
    tlog_config,
)
from edge_landing.cli.run_landing import add_landing_arguments
from edge_landing.cli.run_model import add_model_arguments, choose_files, load_inference  # noqa: F401  (re-exported)
from edge_landing.runtime.core.camera import Mount
from edge_landing.runtime.core.choices import ChoiceEnum
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.fusion.config import FusionConfig
from edge_landing.runtime.fusion.deferred import StageTiming
from edge_landing.runtime.fusion.motion_config import MotionConfig
from edge_landing.runtime.io.autopilot_setup import SetupCheck
from edge_landing.runtime.io.flight_record import TLOG_NAME, FlightRecorder, RecordingSource, check_record_folder
from edge_landing.runtime.io.gimbal import GimbalSeries, GimbalSource
from edge_landing.runtime.io.grabber import Grabber
from edge_landing.runtime.io.mavlink_link import Autopilot, LinkConfig, MavlinkLink, check_url, load_signing_key
from edge_landing.runtime.io.send_rate import check_cap_hz
from edge_landing.runtime.io.sources import SourceConfig, SourceKind, check_source_exists, sim_style_seed
from edge_landing.runtime.io.telemetry import TelemetryBuffer
from edge_landing.runtime.perception.backend import RuntimeRequest
from edge_landing.runtime.perception.precision import Precision
from edge_landing.runtime.pipeline import (
    ContinuityConfig,
    FrameCheck,
    Pipeline,
    PipelineOptions,
    ScaleStage,
    run_record,
)

log = logging.getLogger("edge-run")
RECORD_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v")   # what OpenCV writes with the mp4v codec here


class GridMode(ChoiceEnum):
    NED = "ned"        # the landing grid is kept in local NED across frames (needs LOCAL_POSITION_NED)
    FRAME = "frame"    # a fresh vehicle-centred grid every frame

    @classmethod
    def _label(cls) -> str:
        return "--grid"


@dataclass(frozen=True)
class RunConfig:
    """Everything ``edge-run`` was asked to do (lengths in metres, angles in degrees as typed)."""

    camera: str = "sim"
    camera_width: int = 0
    camera_height: int = 0
    camera_delay_s: float = 0.0         # a live camera's latency its time stamps leave out (an RTSP stream's)
    fps: float = 0.0
    loop: bool = False
    poses: Optional[str] = None
    tlog: Optional[str] = None                 # the flight's MAVLink telemetry log, replayed beside the video
    tlog_video_start: Optional[str] = None     # when the video's first frame was taken, on the log's clock
    model: Optional[str] = None
    depth_model: Optional[str] = None
    hvo_model: Optional[str] = None
    precision: Precision = Precision.AUTO   # auto: the faster of FP32 and its INT8 twin on this CPU
    runtime: RuntimeRequest = RuntimeRequest.AUTO  # auto: OpenVINO too when installed, if faster here and agreeing
    calibration: Optional[str] = None
    altitude_scale: bool = True
    mav: Optional[str] = None
    autopilot: Autopilot = Autopilot.ARDUPILOT
    autopilot_check: SetupCheck = SetupCheck.HOLD   # ArduPilot's PLND_* parameters (io.autopilot_setup)
    mav_sysid: int = 1
    mav_compid: int = 191
    mav_key: Optional[str] = None
    mav_target_system: Optional[int] = None  # take telemetry only from this system id
    hold_s: float = 20.0                     # a committed spot is re-sent from memory at most this long
    target_hz: float = 20.0                  # LANDING_TARGET at most this often on average (0: no cap)
    bridge_s: float = 0.2                    # re-send the newest frame's target when none left for this long (0: off)
    telemetry_wait_s: float = 5.0            # with --mav, wait this long for telemetry before the first frame
    vehicle_radius_m: float = 1.0
    margin_m: float = 1.0
    threads: int = 2
    hfov_deg: float = 90.0
    intrinsics: Optional[str] = None    # a real camera's calibration (JSON, OpenCV or ROS YAML): replaces hfov_deg
    mount_pitch_deg: float = -45.0
    mount_roll_deg: float = 0.0
    mount_yaw_deg: float = 0.0
    gimbal: GimbalSource = GimbalSource.NONE   # mavlink: the camera's orientation as the gimbal reports it, per frame
    record: Optional[str] = None
    flight_record: Optional[str] = None   # a folder: the camera's frames and the link's packets, for a replay
    log_path: Optional[str] = None
    max_frames: int = 0
    duration_s: float = 0.0
    overlap: bool = True
    fusion_hz: float = 0.0              # 0: fuse every frame; else at most this rate (>= 10, the autopilot's need)
    # NED by default: the landing grid stays put in the world while the vehicle moves (falls back to a fresh
    # per-frame grid when telemetry has no position). Fusion accumulates per-frame verdicts there, not raw
    # heights, so the model's frame-to-frame depth scale error (~1 % at 60-80 m) does not break it.
    grid: GridMode = GridMode.NED
    obstacle_height_m: float = 0.5      # motion geometry must resolve this to confirm a spot (§11)
    allow_unconfirmed: bool = False     # send network-only spots (offline images have no motion)
    geometry_timing: StageTiming = StageTiming.OVERLAPPED   # the motion stage beside the frame path (fusion.deferred)
    geometry_width_px: int = 1280       # motion geometry measures frames up to this wide (MotionConfig.max_width_px)

    @property
    def mount(self) -> Mount:
        """The camera's mount as given (--mount-pitch, --mount-roll, --mount-yaw)."""
        return Mount(pitch_rad=math.radians(self.mount_pitch_deg), roll_rad=math.radians(self.mount_roll_deg),
                     yaw_rad=math.radians(self.mount_yaw_deg))

    def __post_init__(self) -> None:
        check_number("--hold", self.hold_s, 0.0, unit="seconds")
        check_number("--duration", self.duration_s, 0.0, unit="seconds")
        check_number("--vehicle-radius", self.vehicle_radius_m, 0.0, lo_open=True, unit="metres")
        check_number("--margin", self.margin_m, 0.0, unit="metres")
        check_number("--obstacle-height", self.obstacle_height_m, 0.0, 10.0, lo_open=True, unit="metres")
        check_number("--geometry-width", self.geometry_width_px, 160, 4096, unit="pixels")
        check_number("--mount-pitch", self.mount_pitch_deg, -90.0, 90.0, unit="degrees")
        check_number("--mount-roll", self.mount_roll_deg, -45.0, 45.0, unit="degrees")
        check_number("--mount-yaw", self.mount_yaw_deg, -180.0, 180.0, unit="degrees")
        check_threads("--threads", self.threads)
        if self.fps != 0:
            check_number("--fps", self.fps, 0.1, 240.0, unit="frames/s (0 = the camera's default)")
        for flag, value, low in (("--mav-sysid", self.mav_sysid, 1), ("--mav-compid", self.mav_compid, 1),
                                 ("--mav-target-system", self.mav_target_system, 1)):
            if value is not None and not low <= value <= 255:
                raise InputError(f"{flag} must be a MAVLink id between {low} and 255, got {value}")
        if self.record and Path(self.record).suffix.lower() not in RECORD_SUFFIXES:
            raise InputError(f"--record {self.record}: the overlay video needs one of the suffixes "
                             f"{', '.join(RECORD_SUFFIXES)}")
        if self.mav:   # before the model is chosen and loaded: a bad address is the one line said
            check_url(self.mav)
            if self.mav_key:
                load_signing_key(self.mav_key)
        if self.mav and not self.altitude_scale and not self.calibration:
            raise InputError("--no-altitude-scale with --mav needs --calibration: without either there is no metric "
                             "depth scale, so no target would ever be sent")
        check_cap_hz(self.target_hz, "--target-hz")
        if self.bridge_s != 0:   # above ArduPilot's 0.5 s it could not keep its estimator's stream going
            check_number("--bridge", self.bridge_s, 0.05, 0.45, unit="seconds (0 = off)")
        if self.fusion_hz != 0 and not 10.0 <= self.fusion_hz <= 1000.0:
            raise InputError(f"--fusion-hz must be 0 (every frame) or 10-1000: targets must update at 10 Hz or "
                             f"faster, got {self.fusion_hz}")
        if not 0 < self.hfov_deg < 180:
            raise InputError(f"--hfov must be in (0, 180) degrees, got {self.hfov_deg}")
        if self.model and (self.depth_model or self.hvo_model):
            raise InputError("give either --model (one joint model) or --depth-model/--hvo-model, not both")
        if bool(self.depth_model) != bool(self.hvo_model) and not self.model:
            raise InputError("--depth-model and --hvo-model go together (or use --model for a joint model)")
        if self.max_frames < 0:
            raise InputError(f"--max-frames must be >= 0 (0 = no limit), got {self.max_frames}")
        if self.camera_width < 0 or self.camera_height < 0:
            raise InputError(f"--camera-width and --camera-height must be >= 0 (0 = the camera's default), "
                             f"got {self.camera_width}, {self.camera_height}")
        check_camera_flags(self.camera, self.camera_delay_s, self.intrinsics, self.poses)
        check_tlog(self.camera, self.tlog, self.tlog_video_start, self.poses, self.loop, self.mav_target_system)
        check_gimbal(self.gimbal, self.mav, self.camera, self.poses, self.tlog)


def build_parser() -> argparse.ArgumentParser:
    p = CliParser(prog="edge-run", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    add_camera_arguments(p)
    add_model_arguments(p)
    add_landing_arguments(p)
    k = p.add_argument_group("MAVLink")
    k.add_argument("--mav", help="pymavlink connection: udpout:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT, /dev/ttyUSB0,57600")
    k.add_argument("--autopilot", default="ardupilot", help="ardupilot (BODY_FRD targets) or px4 (LOCAL_NED)")
    k.add_argument("--autopilot-check", default="hold", help="ArduPilot's precision-landing parameters, read once "
                   "the autopilot is found: hold (default): no target while PLND_ORIENT or PLND_YAW_ALIGN would make "
                   "ArduPilot turn its direction again; warn: only say what is wrong; off: do not read them")
    k.add_argument("--mav-sysid", type=int, default=1)
    k.add_argument("--mav-compid", type=int, default=191)
    k.add_argument("--mav-key", help="MAVLink 2 signing key file (32 bytes, or 64 hex characters)")
    k.add_argument("--mav-target-system", type=int, default=None, help="take telemetry only from this autopilot "
                   "system id (default: the first autopilot HEARTBEAT heard); other senders are ignored")
    k.add_argument("--target-hz", type=float, default=20.0, help="send LANDING_TARGET at most this often on average "
                   "(default 20; 0: every frame's target): a video file or a fast camera gives a target per frame, "
                   "and ArduPilot only uses the newest (2-1000)")
    k.add_argument("--bridge", type=float, default=0.2, help="when no target has left for this long (a slow model "
                   "or camera), re-send the newest frame's sent target at the newest pose, until the next frame is "
                   "decided or it is 1 s old: ArduPilot needs updates < 0.5 s apart (0.05-0.45; 0: off)")
    k.add_argument("--hold", type=float, default=20.0, help="re-send a committed landing spot from memory for at "
                   "most this many seconds without a confirming frame (it is out of view during the vertical descent)")
    o = p.add_argument_group("output")
    o.add_argument("--record", help="overlay video (.mp4)")
    o.add_argument("--log", dest="log_path", help="every decision as JSON lines")
    o.add_argument("--flight-record", metavar="DIR", help="keep the camera's frames (camera.avi, with each frame's "
                   "capture time) and every packet from --mav (link.tlog) in a new folder, to replay the flight later: "
                   "edge-run --camera DIR/camera.avi --tlog DIR/link.tlog")
    o.add_argument("--max-frames", type=int, default=0, help="stop after N frames (0 = no limit)")
    o.add_argument("--duration", type=float, default=0.0, help="stop after S seconds (0 = no limit)")
    return p


def config_from_args(argv: Optional[Sequence[str]]) -> RunConfig:
    a = build_parser().parse_args(argv)
    return RunConfig(camera=a.camera, camera_width=a.camera_width, camera_height=a.camera_height, fps=a.fps,
                     camera_delay_s=a.camera_delay, loop=a.loop, poses=a.poses, tlog=a.tlog,
                     tlog_video_start=a.tlog_video_start, model=a.model, depth_model=a.depth_model, hvo_model=a.hvo_model,
                     precision=Precision.INT8 if a.int8 else Precision.from_string(a.precision),
                     runtime=RuntimeRequest.from_string(a.runtime),
                     calibration=a.calibration, altitude_scale=not a.no_altitude_scale, mav=a.mav,
                     autopilot=Autopilot.from_string(a.autopilot),
                     autopilot_check=SetupCheck.from_string(a.autopilot_check), mav_sysid=a.mav_sysid, mav_compid=a.mav_compid,
                     mav_key=a.mav_key, mav_target_system=a.mav_target_system, hold_s=a.hold,
                     target_hz=a.target_hz, bridge_s=a.bridge,
                     vehicle_radius_m=a.vehicle_radius, margin_m=a.margin, threads=a.threads,
                     hfov_deg=a.hfov, intrinsics=a.intrinsics, mount_pitch_deg=a.mount_pitch, mount_roll_deg=a.mount_roll,
                     mount_yaw_deg=a.mount_yaw, record=a.record, flight_record=a.flight_record,
                     gimbal=GimbalSource.from_string(a.gimbal),
                     log_path=a.log_path,
                     max_frames=a.max_frames, duration_s=a.duration, overlap=not a.sequential, fusion_hz=a.fusion_hz,
                     grid=GridMode.from_string(a.grid), obstacle_height_m=a.obstacle_height,
                     allow_unconfirmed=a.allow_unconfirmed,
                     geometry_timing=StageTiming.from_string(a.geometry_timing), geometry_width_px=a.geometry_width)


def source_record(cfg: RunConfig, kind: SourceKind, model_name: str) -> Dict[str, Any]:
    """The ``--log`` run record: what the frames are (sim world and seed, video, poses) and who consumed them."""
    style: Optional[str] = None
    seed: Optional[int] = None
    if kind in (SourceKind.SIM, SourceKind.SIM_FOLLOW):
        style, seed = sim_style_seed(cfg.camera)
    return run_record(__version__, cfg.camera, kind.value, style, seed, cfg.poses, model_name,
                      cfg.autopilot.value if cfg.mav else None, tlog=cfg.tlog)


def fusion_config(cfg: RunConfig) -> FusionConfig:
    """Fusion's settings from edge-run's landing flags."""
    return FusionConfig(vehicle_radius_m=cfg.vehicle_radius_m, margin_m=cfg.margin_m,
                        obstacle_height_m=cfg.obstacle_height_m, allow_unconfirmed=cfg.allow_unconfirmed,
                        geometry_timing=cfg.geometry_timing, motion=MotionConfig(max_width_px=cfg.geometry_width_px))


def wait_for_telemetry(telemetry: TelemetryBuffer, wait_s: float, out: TextIO) -> None:
    """Give the autopilot a moment before the first frame: without telemetry no target may leave anyway."""
    print(f"edge-run: waiting up to {wait_s:g} s for autopilot telemetry", file=out, flush=True)
    end = time.monotonic() + wait_s
    while time.monotonic() < end:
        if telemetry.lookup(time.monotonic()).fresh:
            return
        time.sleep(0.05)
    log.warning("no fresh autopilot telemetry after %g s (%s): frames are processed, no target is sent until it "
                "arrives", wait_s, telemetry.lookup(time.monotonic()).reason)


def run(cfg: RunConfig, out: Optional[TextIO] = None) -> int:
    out = out or sys.stdout
    from edge_landing.runtime.fusion.fuser import LandingFuser
    from edge_landing.runtime.io.overlay import OverlayRecorder
    from edge_landing.runtime.perception.input_fit import describe_for_model
    from edge_landing.runtime.perception.scale import (
        AltitudeScaleEstimator,
        load_calibration,
    )
    from edge_landing.runtime.pipeline.threads import limit_side_threads

    limit_side_threads()
    check_source_exists(SourceConfig.from_string(cfg.camera))   # one line now, not after seconds of model probing
    inference = load_inference(cfg, out)
    calibration = load_calibration(cfg.calibration, inference.models[0].sha256) if cfg.calibration else None
    src = SourceConfig(camera=cfg.camera, kind=SourceKind.from_string(cfg.camera), width=cfg.camera_width,
                       height=cfg.camera_height, fps=cfg.fps, loop=cfg.loop, poses_csv=cfg.poses or "",
                       delay_s=cfg.camera_delay_s, tlog=tlog_config(cfg.tlog, cfg.tlog_video_start, cfg.mav_target_system))
    fusion_cfg = fusion_config(cfg)
    telemetry = TelemetryBuffer(gimbal=GimbalSeries() if cfg.gimbal is GimbalSource.MAVLINK else None)
    # sim-follow renders the autopilot's pose: with --mav the link's telemetry is the drone's (as in flight),
    # without it the frame's own pose is.
    own_telemetry = (src.kind is SourceKind.SIM or bool(cfg.poses) or bool(cfg.tlog)
                     or (src.kind is SourceKind.SIM_FOLLOW and not cfg.mav))
    recorded = recorded_source(src.kind, cfg.camera, cfg.poses, cfg.tlog)
    link = None
    with contextlib.ExitStack() as stack:
        if cfg.mav:
            # The simulator's (or a replayed flight's) telemetry matches its frames; an autopilot's would
            # describe another flight.
            link_telemetry = TelemetryBuffer() if own_telemetry else telemetry
            tlog_out = str(Path(cfg.flight_record) / TLOG_NAME) if cfg.flight_record else ""
            link = MavlinkLink(LinkConfig(cfg.mav, cfg.autopilot, cfg.mav_sysid, cfg.mav_compid, cfg.mav_key,
                                          target_system=cfg.mav_target_system, tlog_out=tlog_out,
                                          setup_check=cfg.autopilot_check, max_target_hz=cfg.target_hz,
                                          recorded_source=recorded),
                              link_telemetry).start()
            stack.callback(link.stop)
            if recorded:  # said once the link is up, not before a bad --mav is refused
                log.warning("%s: its targets name places in another flight, so they go to the autopilot only while "
                            "it is disarmed%s", recorded,
                            "; its telemetry is its own, not the autopilot's" if own_telemetry else "")
            if not own_telemetry and cfg.telemetry_wait_s > 0:
                wait_for_telemetry(telemetry, cfg.telemetry_wait_s, out)
        grabber = Grabber(src, telemetry=telemetry if own_telemetry else None).start()
        stack.callback(grabber.stop)
        source: Any = grabber
        if cfg.flight_record:   # what the pipeline takes is kept as it came (io.flight_record)
            flight = FlightRecorder(Path(cfg.flight_record), cfg.fps)
            stack.callback(flight.close)
            source = RecordingSource(grabber, flight)
        first = grabber.next(timeout_s=30.0)
        if first is None:
            raise InputError(f"camera {cfg.camera} gave no frame within 30 s"
                             + (" (the input is empty or unreadable)" if grabber.ended else ""))
        grabber.put_back(first)
        intrinsics, mount = camera_geometry(grabber, first, cfg.intrinsics, cfg.hfov_deg, cfg.mount)
        sizes = describe_for_model(inference.models[0], first.rgb.shape[:2], fusion_cfg.working_hw)
        print(f"edge-run: {sizes}", file=out, flush=True)
        fuser = LandingFuser(fusion_cfg, intrinsics, mount)
        estimator = AltitudeScaleEstimator() if cfg.altitude_scale else None
        scale = ScaleStage(calibration, estimator, intrinsics, mount, require_metric=bool(cfg.mav))
        recorder = None
        if cfg.record:
            recorder = OverlayRecorder(cfg.record, intrinsics, mount, fps=cfg.fps or 10.0)
            stack.callback(recorder.close)
        decision_log = stack.enter_context(open(cfg.log_path, "w", buffering=1)) if cfg.log_path else None
        if decision_log is not None:
            decision_log.write(json.dumps(source_record(cfg, src.kind, inference.name)) + "\n")
        # Telemetry is required (trust rules) whenever there is any: an autopilot link or the source's own.
        has_telemetry = bool(cfg.mav) or own_telemetry
        options = PipelineOptions(cfg.max_frames, cfg.duration_s, overlap=cfg.overlap, fusion_max_hz=cfg.fusion_hz,
                                  bridge_s=cfg.bridge_s,
                                  world_grid=cfg.grid is GridMode.NED, mount=mount,
                                  continuity=ContinuityConfig(hold_s=cfg.hold_s,
                                                               min_clearance_m=fusion_cfg.required_clearance_m,
                                                               commit_unconfirmed=cfg.allow_unconfirmed))
        h, w = first.rgb.shape[:2]
        pipeline = Pipeline(source, inference, scale, fuser.fuse, telemetry if has_telemetry else None, link,
                            options, decision_log, recorder, out, FrameCheck(w, h))
        print(f"edge-run: {cfg.camera} -> {inference.name} -> "
              f"{cfg.mav + ' (' + cfg.autopilot.value + ')' if cfg.mav else 'no MAVLink'}; "
              f"need clearance {fusion_cfg.required_clearance_m:.1f} m; Ctrl-C to stop", file=out, flush=True)
        # Ctrl-C, and SIGTERM (systemd or a supervisor stopping the service): stop cleanly, so the log, the overlay
        # video and the summary are complete; Python's default for SIGTERM would end the process mid-write.
        for sig, why in ((signal.SIGINT, "Ctrl-C"), (signal.SIGTERM, "SIGTERM")):
            stack.callback(signal.signal, sig, signal.getsignal(sig))
            signal.signal(sig, lambda *_, why=why: pipeline.stop(why))
        summary = pipeline.run()
    print(summary.table(), file=out, flush=True)
    print(sizes, file=out, flush=True)
    return 0


def _main(argv: Optional[Sequence[str]] = None) -> int:
    cfg = config_from_args(argv)
    for path, what in ((cfg.model, "--model"), (cfg.depth_model, "--depth-model"), (cfg.hvo_model, "--hvo-model"),
                       (cfg.calibration, "--calibration"), (cfg.mav_key, "--mav-key")):
        if path and Path(path).is_dir():
            raise InputError(f"{what} {path} is a folder, expected a file")
        if path and not Path(path).is_file():
            raise InputError(f"{what} file {path} does not exist")
    if cfg.flight_record:
        check_record_folder(cfg.flight_record)
    for path, what in ((cfg.record, "--record"), (cfg.log_path, "--log")):
        if path and not Path(path).resolve().parent.is_dir():
            raise InputError(f"{what} {path}: folder {Path(path).resolve().parent} does not exist")
        if path:
            output_file(path, what)
    from edge_landing.runtime.models import default_model_path

    camera = cfg.camera if Path(cfg.camera).is_file() else None
    shipped = default_model_path()
    check_outputs_spare_inputs({"--log": cfg.log_path, "--record": cfg.record},
                               {"the shipped model": shipped, "the shipped INT8 model": shipped.with_suffix(".int8.onnx"),
                                "--model": cfg.model, "--depth-model": cfg.depth_model, "--hvo-model": cfg.hvo_model,
                                "--calibration": cfg.calibration, "--mav-key": cfg.mav_key, "--poses": cfg.poses,
                                "--tlog": cfg.tlog, "--camera": camera})
    return run(cfg)


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    sys.exit(main())
