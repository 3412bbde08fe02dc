"""edge-run's camera flags: their checks before any work, and the intrinsics and mount at the first frame."""
from __future__ import annotations

import logging
import math
from typing import Optional, Tuple

from edge_landing.cli.common import check_number
from edge_landing.runtime.core.camera import Intrinsics, Mount
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import Frame
from edge_landing.runtime.io.camera_file import fit_to_frame, load_intrinsics
from edge_landing.runtime.io.gimbal import GimbalSource
from edge_landing.runtime.io.grabber import Grabber
from edge_landing.runtime.io.sources import SourceKind

log = logging.getLogger("edge-run")


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


def check_gimbal(gimbal: GimbalSource, mav: Optional[str], camera: str, poses: Optional[str]) -> None:
    """--gimbal mavlink reads the camera's orientation from the autopilot's link, for the frames it describes."""
    kind = SourceKind.from_string(camera)
    if kind is SourceKind.SIM_FOLLOW and "gimbal" in camera.partition("@")[0].split(":") and not mav:
        raise InputError("--camera sim-follow:...:gimbal: a gimballed camera's orientation comes from the "
                         "autopilot's reports, so it needs --mav (and --gimbal mavlink to read them)")
    if gimbal is GimbalSource.NONE:
        return
    if not mav:
        raise InputError("--gimbal mavlink reads the gimbal's reports from the autopilot: it needs --mav")
    if poses or kind is SourceKind.SIM:
        raise InputError("--gimbal mavlink: this input brings its own poses (the sim camera, --poses), not the "
                         "autopilot's, so the gimbal's reports would describe another flight")


def camera_geometry(grabber: Grabber, first: Frame, intrinsics: Optional[str], hfov_deg: float,
                    mount_pitch_deg: float) -> Tuple[Intrinsics, Mount]:
    """Intrinsics at the frame size and the mount: from the synthetic camera when it knows them, else from
    --intrinsics (a calibration file) or --hfov, and --mount-pitch."""
    h, w = first.rgb.shape[:2]
    mount = grabber.mount or Mount(pitch_rad=math.radians(mount_pitch_deg))
    if intrinsics:
        intr = fit_to_frame(load_intrinsics(intrinsics), w, h, intrinsics)
        log.info("intrinsics from %s at %dx%d: fx %.1f, fy %.1f, cx %.1f, cy %.1f px, distortion %s", intrinsics,
                 w, h, intr.fx, intr.fy, intr.cx, intr.cy, list(intr.dist) or "none")
        return intr, mount
    if grabber.intrinsics is not None:
        return grabber.intrinsics.scaled(w, h), mount
    return Intrinsics.from_hfov(w, h, math.radians(hfov_deg)), mount
