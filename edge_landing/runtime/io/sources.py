"""Frame sources (ARCHITECTURE.md §3): what ``--camera`` names, and the readers that open it.

A *reader* opens one kind of input and returns RGB uint8 images one by one (``None`` at the end); the
grabber thread that runs one and stamps its frames is in runtime.io.grabber. Example::

    reader = open_reader(SourceConfig.from_string("flight.mp4"))   # opening problems: one clear InputError
    while (rgb := reader.read()) is not None:
        ...
    reader.close()
"""
from __future__ import annotations

import glob
import logging
import os
import time
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any, List, Optional

import numpy as np

from edge_landing.runtime.core.camera import Intrinsics, Mount
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import VehicleState
from edge_landing.runtime.io.capture_clock import DriverClock

log = logging.getLogger(__name__)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")
STREAM_PREFIXES = ("rtsp://", "rtsps://", "http://", "https://", "udp://", "tcp://", "rtmp://")


class SourceKind(str, Enum):
    DEVICE = "device"
    FILE = "file"
    FOLDER = "folder"
    STREAM = "stream"
    SIM = "sim"
    SIM_FOLLOW = "sim-follow"  # the synthetic camera that renders the autopilot's pose (edge_landing.sim.follow)

    @property
    def live(self) -> bool:
        """Live sources run at their own pace, so the grabber drops what the pipeline cannot take."""
        return self in (SourceKind.DEVICE, SourceKind.STREAM, SourceKind.SIM, SourceKind.SIM_FOLLOW)

    @property
    def real_camera(self) -> bool:
        """A camera device or a stream: its frames' time is the real world's (a latency may be left out)."""
        return self in (SourceKind.DEVICE, SourceKind.STREAM)

    @classmethod
    def from_string(cls, camera: str) -> SourceKind:
        """Guess the kind from what the user typed for ``--camera``."""
        if camera == "sim-follow" or camera.startswith(("sim-follow:", "sim-follow@")):
            return cls.SIM_FOLLOW
        if camera == "sim" or camera.startswith("sim:"):
            return cls.SIM
        if camera.isdigit() or camera.startswith("/dev/video"):
            return cls.DEVICE
        if camera.startswith(STREAM_PREFIXES) or "!" in camera:
            return cls.STREAM
        if any(ch in camera for ch in "*?[") or Path(camera).is_dir():
            return cls.FOLDER
        return cls.FILE


@dataclass(frozen=True)
class SourceConfig:
    """Where frames come from and how to treat faults. width/height/fps = 0 leave the camera's defaults."""

    camera: str
    kind: SourceKind
    width: int = 0
    height: int = 0
    fps: float = 0.0
    loop: bool = False
    poses_csv: str = ""  # replay a recorded flight's poses.csv as telemetry, one row per frame
    tlog: Optional[Any] = None   # a tlog.TlogConfig: replay the flight's MAVLink telemetry log beside its video
    reopen_min_s: float = 0.5
    reopen_max_s: float = 5.0
    # An image identical to the one before is invalid (None: only for a camera device, see RepeatedImage).
    repeats_invalid: Optional[bool] = None
    # A live camera's latency that its frames' time stamps do not include (a stream's: RTSP stamps on arrival),
    # subtracted from them: telemetry is matched to when the image was taken.
    delay_s: float = 0.0

    @property
    def checks_repeats(self) -> bool:
        return self.kind is SourceKind.DEVICE if self.repeats_invalid is None else self.repeats_invalid

    @staticmethod
    def from_string(camera: str, **kwargs: Any) -> SourceConfig:
        return SourceConfig(camera=camera, kind=SourceKind.from_string(camera), **kwargs)


def incomplete_jpeg_or_png(data: bytes) -> str:
    """Why an encoded JPEG/PNG file is incomplete ('' when its end marker is there)."""
    body = data.rstrip(b"\0\r\n ")
    if data[:2] == b"\xff\xd8" and not body.endswith(b"\xff\xd9"):
        return "JPEG without its end-of-image marker (truncated file)"
    if data[:8] == b"\x89PNG\r\n\x1a\n" and b"IEND" not in body[-12:]:
        return "PNG without its IEND chunk (truncated file)"
    return ""


def grey_fill(rgb: np.ndarray) -> str:
    """Why an image looks like an incomplete decode: libjpeg fills what it could not decode with grey 128."""
    last = rgb[-1]
    if last.size and bool(np.all(last == 128)):
        return "bottom row is uniform grey 128 (an incompletely decoded JPEG frame)"
    return ""


class RepeatedImage:
    """An image identical, bit for bit, to the previous one from a live sensor is a stale buffer handed over
    again (a capture card or driver that repeats its last frame when the camera stalls): a sensor's noise
    alone makes two real exposures differ. Geometry would pair it with the vehicle's new pose and read the
    wrong motion, and the network's view of it is already old, so the frame is invalid. Only for camera
    devices: a compressed stream or a recorded flight may legitimately repeat an image (a hover over a
    static scene). Keeps a reference to the last image only."""

    def __init__(self) -> None:
        self._last: Optional[np.ndarray] = None

    def check(self, image: np.ndarray) -> str:
        last, self._last = self._last, image
        if last is None or last.shape != image.shape:
            return ""
        # a sparse sample rejects almost every real pair at once; the whole image only when that matched
        if not np.array_equal(last[::8, ::8], image[::8, ::8]) or not np.array_equal(last, image):
            return ""
        return "identical to the previous image (the camera handed over a stale buffer again: frozen feed)"


class Reader:
    """One opened input. ``read`` returns RGB uint8 H×W×3, or None at the end of a recorded input;
    it raises OSError when a live device fails (the grabber then reopens it). ``problem`` says why the last
    image is not to be trusted ('' when it is), ``intrinsics``/``mount`` are known by a synthetic camera,
    ``last_state`` is the vehicle state of the last image when the source knows it (sim, pose replay),
    ``capture_time_s`` the monotonic time the last image was taken when the source knows it (sim-follow),
    ``sim_time_s`` the flight's own time of the last image when the source simulates or replays a flight
    (the sim camera, a pose replay): the grabber maps it onto a monotonic base fixed at the first frame."""

    name = ""
    problem = ""
    intrinsics: Optional[Intrinsics] = None
    mount: Optional[Mount] = None
    last_state: Optional[VehicleState] = None
    capture_time_s: Optional[float] = None  # time.monotonic() when the last image was taken, if the reader knows
    sim_time_s: Optional[float] = None      # the simulated flight's time of the last image (s), if it has one

    def read(self) -> Optional[np.ndarray]:
        raise NotImplementedError

    def close(self) -> None:
        pass

    def feed_telemetry(self, telemetry: Any, capture_time_s: float) -> None:
        """Give ``telemetry`` (a TelemetryBuffer) what this source knows of the vehicle up to the image just
        read, stamped ``capture_time_s`` on the grabber's clock: a simulated or pose-replayed frame's state."""
        if self.last_state is not None:
            # Sampled and arrived at the frame's time: freshness is judged on the frame's clock (Frame.clock_lag_s).
            telemetry.add_state(self.last_state, capture_time_s, arrival_s=capture_time_s)


class VideoReader(Reader):
    """cv2.VideoCapture over a V4L2 device, a video file or a stream URL. A device's frames carry the driver's
    capture time where it is on this clock (``capture_clock.py``); the others are stamped by the grabber."""

    def __init__(self, config: SourceConfig):
        import cv2

        self.config = config
        self.name = config.camera
        self._expected_frames = 0
        self._read = 0
        self._repeats = RepeatedImage() if config.checks_repeats else None
        self._clock = DriverClock(config.camera) if config.kind is SourceKind.DEVICE else None
        target: int | str = config.camera
        if config.kind is SourceKind.DEVICE:
            target = int(config.camera) if config.camera.isdigit() else config.camera
            check_source_exists(config)
            self.cap = cv2.VideoCapture(target, cv2.CAP_V4L2)
            self.cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the driver's queue would add latency; we want the newest
            if config.width and config.height:
                self.cap.set(cv2.CAP_PROP_FRAME_WIDTH, config.width)
                self.cap.set(cv2.CAP_PROP_FRAME_HEIGHT, config.height)
            if config.fps:
                self.cap.set(cv2.CAP_PROP_FPS, config.fps)
        elif config.kind is SourceKind.FILE:
            check_source_exists(config)
            self.cap = cv2.VideoCapture(config.camera)
            self._expected_frames = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        else:
            api = cv2.CAP_GSTREAMER if "!" in config.camera else cv2.CAP_FFMPEG
            self.cap = cv2.VideoCapture(config.camera, api)
        if not self.cap.isOpened():
            what = {SourceKind.DEVICE: "camera device", SourceKind.FILE: "video file",
                    SourceKind.STREAM: "stream"}[config.kind]
            hint = " (truncated or corrupt, or a codec OpenCV cannot read)" if config.kind is SourceKind.FILE else ""
            raise InputError(f"cannot open {what} {target}{hint}")

    def read(self) -> Optional[np.ndarray]:
        import cv2

        ok, bgr = self.cap.read()
        if not ok or bgr is None:
            if self.config.kind is SourceKind.FILE:
                if self._expected_frames and self._read < self._expected_frames - 1:
                    log.warning("video %s ended early after %d of %d frames (truncated or corrupt); stopping cleanly",
                                self.name, self._read, self._expected_frames)
                return None
            raise OSError(f"{self.name}: no frame from the camera")
        clock_problem = ""
        if self._clock is not None:
            self.capture_time_s, clock_problem = self._clock.capture_time_s(self.cap.get(cv2.CAP_PROP_POS_MSEC),
                                                                            time.monotonic())
        self._read += 1
        repeated = self._repeats.check(bgr) if self._repeats is not None else ""
        self.problem = grey_fill(bgr) or repeated or clock_problem
        if bgr.ndim == 2:
            return cv2.cvtColor(bgr, cv2.COLOR_GRAY2RGB)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def close(self) -> None:
        self.cap.release()


class ImageFolderReader(Reader):
    """Every image of a folder (sorted) or a glob; an unreadable image is skipped with a warning."""

    def __init__(self, config: SourceConfig):
        pattern = config.camera
        paths = _folder_images(pattern)
        if not paths:
            raise InputError(_no_images(pattern))
        self.name = pattern
        self.paths: List[Path] = paths
        self._next = 0

    def read(self) -> Optional[np.ndarray]:
        import cv2

        while self._next < len(self.paths):
            path = self.paths[self._next]
            self._next += 1
            try:
                data = path.read_bytes()
            except OSError as exc:
                log.warning("skipping %s: %s", path, exc)
                continue
            # imread, not imdecode: imdecode refuses a truncated JPEG, imread decodes it with grey rows, and the
            # marker check below then marks the frame invalid (it is counted and logged, not silently skipped).
            bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if bgr is not None:
                self.problem = incomplete_jpeg_or_png(data) or grey_fill(bgr)
                return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            log.warning("skipping %s: not a readable image (corrupt or not an image)", path)
        return None


def check_source_exists(config: SourceConfig) -> None:
    """Raise the one-line InputError that opening ``config`` would raise for an input that is not there (a missing
    device node, video file or image folder; a sim camera without the ``[sim]`` extra), without opening it:
    edge-run asks before it loads and probes the networks, which takes seconds."""
    kind, camera = config.kind, config.camera
    if kind is SourceKind.DEVICE:
        node = f"/dev/video{camera}" if camera.isdigit() else camera
        if os.path.isdir("/dev") and not os.path.exists(node):
            raise InputError(f"camera {node} not found (no such device); expected a V4L2 device such as "
                             f"/dev/video0 or an index; present: {sorted(glob.glob('/dev/video*')) or 'none'}")
    elif kind is SourceKind.FILE and not Path(camera).is_file():
        raise InputError(f"video file {camera} does not exist; expected a video (mp4, avi, ...), an image "
                         f"folder or glob, a /dev/video device, an rtsp:// URL or 'sim'")
    elif kind is SourceKind.FOLDER and not _folder_images(camera):
        raise InputError(_no_images(camera))
    elif kind in (SourceKind.SIM, SourceKind.SIM_FOLLOW):
        check_sim_extra(kind.value)
        from edge_landing.runtime.core.errors import require_extra

        if kind is SourceKind.SIM:
            require_extra("edge_landing.sim", "sim").Style.from_string(sim_style_seed(camera)[0])
        else:
            require_extra("edge_landing.sim.follow", "sim").FollowSpec.parse(camera)


def sim_style_seed(camera: str) -> tuple[str, int]:
    """(style, seed) of ``sim[:STYLE][:SEED]`` or ``sim-follow[:STYLE[:SEED]][:gimbal][@URL]``: suburban and 0
    where not given (the style is not checked here)."""
    style, seed = "suburban", 0
    for part in camera.partition("@")[0].split(":")[1:]:
        if part.isdigit():
            seed = int(part)
        elif part and part != "gimbal":
            style = part
    return style, seed


def _folder_images(pattern: str) -> List[Path]:
    """The images of a folder or a glob, sorted."""
    if Path(pattern).is_dir():
        return sorted(p for p in Path(pattern).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    return sorted(Path(p) for p in glob.glob(pattern) if Path(p).suffix.lower() in IMAGE_SUFFIXES)


def _no_images(pattern: str) -> str:
    return f"no images found at {pattern}; expected a folder or glob of {'/'.join(s[1:] for s in IMAGE_SUFFIXES)} files"


def check_sim_extra(camera: str) -> None:
    """Raise one MissingExtraError line when the ``[sim]`` extra is absent, before any work (worlds are built
    lazily, so a missing ray caster would otherwise show up after the "building the world" line)."""
    import importlib.util

    from edge_landing.runtime.core.errors import MissingExtraError

    for needed in ("trimesh", "embreex"):
        if importlib.util.find_spec(needed) is None:
            raise MissingExtraError(f"the {camera} camera needs '{needed}', which is not installed: "
                                    "pip install 'edge-landing[sim]'")


class SimReader(Reader):
    """The synthetic camera of the ``sim`` package (the ``[sim]`` extra), imported only when asked for.

    ``--camera sim[:STYLE][:SEED]``, e.g. ``sim``, ``sim:urban``, ``sim:urban:3``. It flies one landing approach
    (approach, hover, descent; ``FLIGHT_FRAMES`` frames) in real time at ``fps`` (default 10) and then ends, or
    repeats it with ``--loop``. Like a camera with perfect telemetry, it gives the vehicle state of each frame
    (``last_state``), which the grabber feeds to the telemetry buffer at the capture time.
    """

    FLIGHT_FRAMES = 200

    # 640×480: motion geometry (ARCHITECTURE.md §11) needs the camera's own pixels to confirm a spot; at
    # 160×120 a DIS patch covers > 1.5 m of ground beyond ~15 m and nothing is ever confirmed. Renders
    # 200 frames in about a minute on one busy core.
    DEFAULT_SIZE = (640, 480)

    def __init__(self, config: SourceConfig):
        from edge_landing.runtime.core.errors import require_extra

        check_sim_extra("sim")
        sim = require_extra("edge_landing.sim", "sim")
        style, seed = sim_style_seed(config.camera)
        sim.Style.from_string(style)   # an unknown style fails in one line here, before the world is built
        width, height = (config.width, config.height) if config.width and config.height else self.DEFAULT_SIZE
        log.info("building the synthetic %s world (seed %d) for the sim camera...", style, seed)
        self.camera = sim.SimCamera(style=style, seed=seed, width=width, height=height, fps=config.fps or 10.0,
                                    flight_frames=self.FLIGHT_FRAMES, realtime=True)
        self._frames_left = None if config.loop else self.FLIGHT_FRAMES
        self.name = f"sim:{style}:{seed}"
        self.intrinsics = self.camera.intrinsics
        self.mount = self.camera.mount

    def read(self) -> Optional[np.ndarray]:
        if self._frames_left is not None:
            if self._frames_left <= 0:
                return None  # the flight is over: end the run cleanly
            self._frames_left -= 1
        rgb, _pose, self.last_state = self.camera.read()
        self.sim_time_s = self.last_state.time_s
        out: np.ndarray = rgb
        return out

    def close(self) -> None:
        self.camera.close()


def open_reader(config: SourceConfig) -> Reader:
    if config.kind is SourceKind.FOLDER:
        reader: Reader = ImageFolderReader(config)
    elif config.kind is SourceKind.SIM:
        return SimReader(config)
    elif config.kind is SourceKind.SIM_FOLLOW:
        return open_follow_reader(config)
    else:
        reader = VideoReader(config)
    try:
        if config.poses_csv:
            from edge_landing.runtime.io.replay import PoseReplayReader

            return PoseReplayReader(reader, PoseReplayReader.states_from_csv(config.poses_csv))
        if config.tlog is not None:
            from edge_landing.runtime.io.replay import TlogReplayReader

            return TlogReplayReader(reader, config.tlog, config.fps)
    except Exception:
        reader.close()
        raise
    return reader


def open_follow_reader(config: SourceConfig) -> Reader:
    """``--camera sim-follow[:STYLE[:SEED]][@URL]``: renders the world from the autopilot's pose (``[sim]`` extra)."""
    from edge_landing.runtime.core.errors import require_extra

    check_sim_extra("sim-follow")
    follow = require_extra("edge_landing.sim.follow", "sim")
    reader: Reader = follow.FollowReader(config)
    return reader
