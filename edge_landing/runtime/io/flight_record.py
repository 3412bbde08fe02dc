"""A flight recorder for a later replay on the desk (``edge-run --flight-record DIR``, ARCHITECTURE.md §4).

In flight it keeps what edge-run saw, so that the same flight can be replayed with ``edge-run --camera
DIR/camera.avi --tlog DIR/link.tlog``:
- ``camera.avi``: every valid frame the pipeline took, as it came from the camera (MJPG; written by a thread
  of its own through a short queue, so a slow disk costs recorded frames, counted, never the pipeline's time);
- ``camera.frames.csv``: each recorded frame's capture time on the UNIX clock (the clock a .tlog's arrival
  times are on), so the replay times frames as they were taken, not by the container's nominal rate;
- ``link.tlog``: every packet the MAVLink link received, after its arrival time (``tlog.TlogWriter``, written
  by the link).
"""
from __future__ import annotations

import csv
import logging
import math
import os
import queue
import threading
import time
from pathlib import Path
from typing import Any, List, Optional

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import Frame

__all__ = ["FlightRecorder", "RecordingSource", "VIDEO_NAME", "TLOG_NAME", "frame_times_beside", "check_record_folder",
           "unix_time"]
log = logging.getLogger(__name__)

VIDEO_NAME, TIMES_SUFFIX, TLOG_NAME = "camera.avi", ".frames.csv", "link.tlog"
TIMES_FIELDS = ("index", "frame", "capture_unix_s")


_UNIX_MINUS_MONOTONIC_S: list[float] = []


def unix_time(monotonic_s: float) -> float:
    """A monotonic time on the UNIX clock, by one offset taken once per process. The recorder's frame times and
    link.tlog's arrival times share it, so a wall clock stepped in flight (NTP finding a network on a companion
    computer without a real-time clock) moves neither against the other."""
    if not _UNIX_MINUS_MONOTONIC_S:
        _UNIX_MINUS_MONOTONIC_S.append(time.time() - time.monotonic())
    return monotonic_s + _UNIX_MINUS_MONOTONIC_S[0]


def times_path(video: str | os.PathLike[str]) -> Path:
    return Path(video).with_suffix(TIMES_SUFFIX)


def frame_times_beside(video: str | os.PathLike[str]) -> Optional[List[float]]:
    """The capture times (UNIX s, in video order) recorded beside a video by the flight recorder, or None when
    there are none; a sidecar that cannot be read is an InputError naming it."""
    path = times_path(video)
    if not Path(video).is_file() or not path.is_file():
        return None
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
        times = [float(r["capture_unix_s"]) for r in rows]
    except (OSError, KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: not the flight recorder's frame times ({exc}); expected columns "
                         f"{','.join(TIMES_FIELDS)}") from None
    if not times or not all(math.isfinite(t) for t in times) or any(b <= a for a, b in zip(times, times[1:])):
        raise InputError(f"{path}: frame times must be finite and increasing, one row per recorded frame")
    return times


def check_record_folder(folder: str) -> Path:
    """The folder the recorder will write, created; one that already holds a recording is refused (nothing
    already written is lost)."""
    path = Path(folder)
    if path.exists() and not path.is_dir():
        raise InputError(f"--flight-record {folder} exists and is not a folder")
    taken = [n for n in (VIDEO_NAME, Path(VIDEO_NAME).stem + TIMES_SUFFIX, TLOG_NAME) if (path / n).exists()]
    if taken:
        raise InputError(f"--flight-record {folder} already holds a recording ({', '.join(taken)}); give a new folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--flight-record {folder} cannot be created ({exc.strerror or exc})") from None
    if not os.access(path, os.W_OK):
        raise InputError(f"--flight-record {folder} is not writable")
    return path


class FlightRecorder:
    """Records frames (``add``) into ``folder``/camera.avi and its frame times; ``close`` flushes both."""

    def __init__(self, folder: Path, fps: float, queue_frames: int = 8):
        self.folder, self.fps = folder, fps if fps > 0 else 10.0
        self.recorded = self.dropped = 0
        self._queue: queue.Queue[Optional[Frame]] = queue.Queue(maxsize=queue_frames)
        self._writer: Any = None
        self._times = open(times_path(folder / VIDEO_NAME), "w", newline="")
        self._csv = csv.writer(self._times)
        self._csv.writerow(TIMES_FIELDS)
        self._thread = threading.Thread(target=self._run, name="flight-record", daemon=True)
        self._thread.start()

    def add(self, frame: Frame) -> None:
        """Queue a frame for recording (never blocks; a full queue drops it, counted)."""
        if not frame.valid:
            return
        try:
            self._queue.put_nowait(frame)
        except queue.Full:
            self.dropped += 1

    def _run(self) -> None:
        while (frame := self._queue.get()) is not None:
            try:
                self._write(frame)
            except Exception as exc:   # a full disk must not stop the flight: recording ends, said once
                log.warning("--flight-record: writing %s failed (%s); recording stopped", self.folder, exc)
                self.dropped += 1 + self._queue.qsize()
                return

    def _write(self, frame: Frame) -> None:
        import cv2

        h, w = frame.rgb.shape[:2]
        if self._writer is None:
            self._writer = cv2.VideoWriter(str(self.folder / VIDEO_NAME), cv2.VideoWriter.fourcc(*"MJPG"), self.fps,
                                           (w, h))
            self._writer.set(cv2.VIDEOWRITER_PROP_QUALITY, 95)
            self._size = (w, h)
        if (w, h) != self._size:    # a video holds one size: a camera that changed mode is not recorded further
            self.dropped += 1
            return
        self._writer.write(cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
        self._csv.writerow((self.recorded, frame.frame_id, f"{unix_time(frame.capture_time_s):.6f}"))
        self.recorded += 1

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(timeout=10.0)
        if self._writer is not None:
            self._writer.release()
        self._times.close()
        log.info("--flight-record %s: %d frames recorded, %d dropped", self.folder, self.recorded, self.dropped)


class RecordingSource:
    """A frame source (pipeline.protocols.FrameSource) that records every frame it hands to the pipeline."""

    def __init__(self, source: Any, recorder: FlightRecorder):
        self.source, self.recorder = source, recorder

    @property
    def ended(self) -> bool:
        return bool(self.source.ended)

    @property
    def drops(self) -> int:
        return int(self.source.drops)

    @property
    def faults(self) -> int:
        return int(self.source.faults)

    def next(self, timeout_s: float = 1.0) -> Optional[Frame]:
        frame: Optional[Frame] = self.source.next(timeout_s)
        if frame is not None:
            self.recorder.add(frame)
        return frame
