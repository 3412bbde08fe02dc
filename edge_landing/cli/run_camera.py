"""edge-run's camera flags: their checks before any work, and the intrinsics and mount at the first frame."""
from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path
from typing import Optional, Tuple

from edge_landing.cli.common import check_number
from edge_landing.runtime.core.camera import Intrinsics, Mount
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import Frame
from edge_landing.runtime.io.camera_file import fit_to_frame, load_intrinsics
from edge_landing.runtime.io.flight_record import frame_times_beside
from edge_landing.runtime.io.gimbal import GimbalSource
from edge_landing.runtime.io.grabber import Grabber
from edge_landing.runtime.io.sources import SourceKind
from edge_landing.runtime.io.tlog import START_FORMS, TlogConfig, TlogTelemetry

log = logging.getLogger("edge-run")


def add_camera_arguments(parser: argparse.ArgumentParser) -> None:
    """edge-run's "camera" group: the input, its geometry and the telemetry a recording brings."""
    src = parser.add_argument_group("camera")
    src.add_argument("--camera", default="sim", help="/dev/videoN or index, video file, image folder or glob, "
                     "rtsp://... or GStreamer pipeline, or 'sim' (default: the built-in synthetic flight)")
    src.add_argument("--camera-width", type=int, default=0)
    src.add_argument("--camera-height", type=int, default=0)
    src.add_argument("--fps", type=float, default=0.0, help="camera frame rate to ask for (0 = its default)")
    src.add_argument("--camera-delay", type=float, default=0.0, help="seconds from exposure to a frame's time "
                     "stamp that the stamp leaves out: an RTSP stream's latency (stamped on arrival), subtracted")
    src.add_argument("--loop", action="store_true", help="repeat a video file or image folder (or the sim flight)")
    src.add_argument("--poses", help="replay a recorded flight's poses.csv (edge-sim --flight) as telemetry, "
                     "one row per frame")
    src.add_argument("--tlog", help="replay a recorded video (or image folder) with the MAVLink telemetry log of the "
                     "same flight (.tlog, from QGroundControl, Mission Planner, MAVProxy or mavlink-router): its "
                     "telemetry passes every check the live link's does")
    src.add_argument("--tlog-video-start", help="with --tlog: when the video's first frame was taken, on the log's "
                     "clock: UNIX seconds, an ISO 8601 time with its zone (2026-11-24T10:00:03.2Z), or +S (seconds "
                     "after the log's first packet); not needed for a --flight-record video, whose frame times "
                     "are beside it")
    src.add_argument("--hfov", type=float, default=90.0, help="camera horizontal field of view, degrees")
    src.add_argument("--intrinsics", help="the camera's calibration instead of --hfov: JSON (fx, fy, cx, cy, dist, "
                     "width, height), OpenCV FileStorage YAML/XML or ROS camera_info YAML, with lens distortion")
    src.add_argument("--mount-pitch", type=float, default=-45.0, help="camera pitch relative to the body, degrees "
                     "(negative = below the horizon)")
    src.add_argument("--mount-roll", type=float, default=0.0, help="camera roll about its optical axis, "
                     "degrees (positive: the camera's right side down, as a vehicle rolls)")
    src.add_argument("--mount-yaw", type=float, default=0.0, help="camera yaw relative to the body's nose, degrees "
                     "(positive = to the right)")
    src.add_argument("--gimbal", default="none", help="mavlink: the camera is on a gimbal whose orientation comes "
                     "from --mav or --tlog (GIMBAL_DEVICE_ATTITUDE_STATUS), per frame; none (default): --mount-pitch, "
                     "fixed")


def check_camera_flags(camera: str, delay_s: float, intrinsics: Optional[str], poses: Optional[str]) -> None:
    """One InputError naming the flag when --camera-delay, --intrinsics or --poses does not fit --camera."""
    kind = SourceKind.from_string(camera)
    if poses and kind is SourceKind.SIM:
        raise InputError("--poses replays a recorded flight's telemetry; the sim camera has its own")
    check_number("--camera-delay", delay_s, 0.0, 2.0, unit="seconds")
    if delay_s and not kind.real_camera:
        raise InputError("--camera-delay is a live camera's or stream's latency; this input's frames are stamped "
                         "by the flight or when the pipeline takes them")
    if intrinsics:
        if kind in (SourceKind.SIM, SourceKind.SIM_FOLLOW):
            raise InputError("--intrinsics describes a real camera's lens; the synthetic camera has its own")
        load_intrinsics(intrinsics)   # a bad file is the one line said, before the model loads


def tlog_config(path: Optional[str], video_start: Optional[str], target_system: Optional[int]) -> Optional[TlogConfig]:
    return TlogConfig(path, video_start or "", target_system=target_system) if path else None


def check_tlog(camera: str, path: Optional[str], video_start: Optional[str], poses: Optional[str], loop: bool,
               target_system: Optional[int]) -> None:
    """--tlog replays a recording with its flight's telemetry log: one InputError naming what does not fit. The log
    is opened and --tlog-video-start read here, so a bad file or time is said before the model loads."""
    if video_start and not path:
        raise InputError("--tlog-video-start times a video against a telemetry log: it needs --tlog")
    if not path:
        return
    kind = SourceKind.from_string(camera)
    if kind not in (SourceKind.FILE, SourceKind.FOLDER):
        raise InputError(f"--tlog replays a recorded video or image folder with its flight's log; --camera {camera} "
                         f"is not a recording")
    if poses:
        raise InputError("give --poses or --tlog, not both: each is the recording's telemetry")
    if loop:
        raise InputError("--loop with --tlog: the log's telemetry does not repeat with the video")
    recorded = frame_times_beside(camera)   # a flight recorder's video says when each frame was taken
    if not video_start and not recorded:
        raise InputError(f"--tlog needs --tlog-video-start: when the video's first frame was taken, on the log's "
                         f"clock ({START_FORMS}); a --flight-record video has it beside it")
    start = video_start or (f"{recorded[0]:.6f}" if recorded else "")
    TlogTelemetry(TlogConfig(path, start, target_system=target_system)).close()


def check_gimbal(gimbal: GimbalSource, mav: Optional[str], camera: str, poses: Optional[str],
                 tlog: Optional[str] = None) -> None:
    """--gimbal mavlink reads the camera's orientation from the autopilot's reports, live (--mav) or as a flight's
    telemetry log recorded them (--tlog), for the frames they describe (not a --poses replay's or the sim's)."""
    kind = SourceKind.from_string(camera)
    if kind is SourceKind.SIM_FOLLOW and "gimbal" in camera.partition("@")[0].split(":") and not mav:
        raise InputError("--camera sim-follow:...:gimbal: a gimballed camera's orientation comes from the "
                         "autopilot's reports, so it needs --mav (and --gimbal mavlink to read them)")
    if gimbal is GimbalSource.NONE:
        return
    if not mav and not tlog:
        raise InputError("--gimbal mavlink reads the gimbal's reports from the autopilot: it needs --mav (or --tlog "
                         "for a recorded flight)")
    if poses or kind is SourceKind.SIM:
        raise InputError("--gimbal mavlink: this input brings its own poses (the sim camera, --poses), not the "
                         "autopilot's, so the gimbal's reports would describe another flight")


def camera_geometry(grabber: Grabber, first: Frame, intrinsics: Optional[str], hfov_deg: float,
                    given_mount: Mount) -> Tuple[Intrinsics, Mount]:
    """Intrinsics at the frame size and the mount: from the synthetic camera when it knows them, else from
    --intrinsics (a calibration file) or --hfov, and --mount-pitch/--mount-roll/--mount-yaw (``given_mount``)."""
    h, w = first.rgb.shape[:2]
    mount = grabber.mount or given_mount
    if intrinsics:
        intr = fit_to_frame(load_intrinsics(intrinsics), w, h, intrinsics)
        log.info("intrinsics from %s at %dx%d: fx %.1f, fy %.1f, cx %.1f, cy %.1f px, distortion %s", intrinsics,
                 w, h, intr.fx, intr.fy, intr.cx, intr.cy, list(intr.dist) or "none")
        return intr, mount
    if grabber.intrinsics is not None:
        return grabber.intrinsics.scaled(w, h), mount
    return Intrinsics.from_hfov(w, h, math.radians(hfov_deg)), mount


def recorded_source(kind: SourceKind, camera: str, poses: Optional[str], tlog: Optional[str]) -> str:
    """What the frames are when they are not this flight's live view (LinkConfig.recorded_source), '' when they
    are: a camera device, a stream, a pipe, or the synthetic camera that renders the autopilot's own pose."""
    if kind is SourceKind.SIM:
        return "sim camera"
    if tlog:
        return "--tlog replay"
    if poses:
        return "--poses replay"
    if kind is SourceKind.FOLDER:
        return "image folder"
    if kind is SourceKind.FILE and Path(camera).is_file():   # a FIFO a live pipeline writes is not a recording
        return "recorded video"
    return ""
