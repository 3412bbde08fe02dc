"""The grabber thread (ARCHITECTURE.md §3: every frame has an id and a monotonic capture time).

The :class:`Grabber` runs a reader (runtime.io.sources) in its own thread. Live sources (a V4L2 camera, an
RTSP/GStreamer stream, the synthetic camera) keep only the newest frame and count the ones the pipeline never
saw; recorded ones (a video file, an image folder) hand over every frame, so a file run is repeatable. Example::

    grabber = Grabber(SourceConfig.from_string("flight.mp4"))
    grabber.start()                       # opening problems raise one clear InputError here
    while (frame := grabber.next(timeout_s=1.0)) is not None or not grabber.ended:
        ...
    grabber.stop()
"""
from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any, Callable, Optional

from edge_landing.runtime.core.camera import Intrinsics, Mount
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import Frame
from edge_landing.runtime.io.sources import Reader, SourceConfig, open_reader

log = logging.getLogger(__name__)


class Grabber:
    """Reads frames in a thread; live sources keep only the newest frame and count drops.

    ``opener`` turns the config into a :class:`Reader` (default :func:`open_reader`); it is called again to
    reopen a failed live source.
    """

    def __init__(self, config: SourceConfig, opener: Optional[Callable[[SourceConfig], Reader]] = None,
                 telemetry: Optional[Any] = None):
        self.config = config
        self.opener = opener or open_reader
        self.telemetry = telemetry  # a TelemetryBuffer fed with the states of a simulated source
        self.reader: Optional[Reader] = None
        self.drops = 0
        self.grabbed = 0
        self.faults = 0
        self.ended = False
        self._slot: Optional[Frame] = None
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._next_id = 0
        self._front: Optional[Frame] = None
        self._sim_base_s: Optional[float] = None   # monotonic time of a simulated flight's t = 0
        self._last_stamp_s = -float("inf")
        self._problem = ""            # the reason of the current run of invalid frames ('' while frames are fine)
        self._problem_frames = 0

    def put_back(self, frame: Frame) -> None:
        """Hand ``frame`` out again at the next ``next`` (the caller looked at the first frame before the loop)."""
        self._front = frame

    @property
    def intrinsics(self) -> Optional[Intrinsics]:
        return None if self.reader is None else self.reader.intrinsics

    @property
    def mount(self) -> Optional[Mount]:
        return None if self.reader is None else self.reader.mount

    def start(self) -> Grabber:
        """Open the input now (so a missing camera is one clear error) and start the thread."""
        self.reader = self.opener(self.config)
        self._thread = threading.Thread(target=self._run, name="grabber", daemon=True)
        self._thread.start()
        return self

    def next(self, timeout_s: float = 1.0) -> Optional[Frame]:
        """The newest frame not yet taken, or None after ``timeout_s`` or at the end."""
        if self._front is not None:
            front, self._front = self._front, None
            return front
        with self._cond:
            if self._slot is None and not self.ended:
                self._cond.wait(timeout_s)
            frame, self._slot = self._slot, None
            self._cond.notify_all()
            return frame

    def stop(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=3.0)
        if self.reader is not None:
            self.reader.close()

    # -- the thread -----------------------------------------------------------------------------------
    def _run(self) -> None:
        backoff_s = self.config.reopen_min_s
        while not self._stop.is_set():
            if self.reader is None:
                if not self._reopen(backoff_s):
                    if not self.config.kind.live:
                        break  # a recorded input that vanished while looping: end cleanly
                    backoff_s = min(backoff_s * 2.0, self.config.reopen_max_s)
                    continue
                backoff_s = self.config.reopen_min_s
            reader = self.reader
            assert reader is not None  # opened just above
            try:
                rgb = reader.read()
            except Exception as exc:  # a mid-run camera fault never stops the loop: reopen with back-off
                self.faults += 1
                log.warning("camera %s failed (%s); reopening with back-off", self.config.camera, exc)
                reader.close()
                self.reader = None
                continue
            if rgb is None:
                if self.config.loop and not self.config.kind.live:
                    reader.close()
                    self.reader = None
                    continue
                break
            if not self.config.kind.live:
                # Recorded input has no real capture time: stamp it when the pipeline can take it, so a slow
                # model does not make every played-back frame "stale".
                self._wait_for_free_slot()
            problem = reader.problem
            self._say_problem(problem)
            stamp_s, lag_s = self._stamp(reader)
            frame = Frame(self._next_id, stamp_s, rgb, self.config.camera, valid=not problem, reason=problem,
                          clock_lag_s=lag_s)
            if self.telemetry is not None:
                reader.feed_telemetry(self.telemetry, frame.capture_time_s)
            self._publish(frame)
            self._next_id += 1
        with self._cond:
            self.ended = True
            self._cond.notify_all()

    def _say_problem(self, problem: str) -> None:
        """Log the first frame of a run of invalid frames with one reason, and the run's length when it ends
        (a frozen camera at 30 frames/s would otherwise write 30 lines a second)."""
        if problem == self._problem:
            self._problem_frames += bool(problem)
            return
        if self._problem:
            log.warning("%d frame(s) of %s were invalid: %s", self._problem_frames, self.config.camera, self._problem)
        if problem:
            log.warning("frame %d of %s is invalid: %s", self._next_id, self.config.camera, problem)
        self._problem, self._problem_frames = problem, int(bool(problem))

    def _stamp(self, reader: Reader) -> tuple[float, float]:
        """(capture time, clock lag) of the image just read (see Frame.clock_lag_s).

        A reader that knows when its image was taken on this clock (sim-follow: the pose's time, a V4L2 device:
        the driver's stamp) says so; a live camera's ``delay_s`` is subtracted from that or from its arrival. A
        simulated or replayed flight gives its own time, mapped onto a monotonic base fixed at its first frame,
        so that which frames geometry pairs and what the grids remember depend on the flight only, not on how
        fast it rendered (with wall-clock stamps the default sim run's target count varied between runs). The
        base moves forward only when the flight's time goes back (a replay restarting with --loop)."""
        now = time.monotonic()
        delay = self.config.delay_s if self.config.kind.real_camera else 0.0
        if reader.capture_time_s is not None:
            return reader.capture_time_s - delay, 0.0
        sim_s = reader.sim_time_s
        if sim_s is None or not math.isfinite(sim_s):
            return now - delay, 0.0
        if self._sim_base_s is None or self._sim_base_s + sim_s <= self._last_stamp_s:
            self._sim_base_s = max(now, self._last_stamp_s + 1e-3) - sim_s
        stamp = self._sim_base_s + sim_s
        self._last_stamp_s = stamp
        return stamp, now - stamp

    def _reopen(self, backoff_s: float) -> bool:
        if self._stop.wait(backoff_s if self.config.kind.live else 0.0):
            return False
        try:
            self.reader = self.opener(self.config)
        except (InputError, OSError) as exc:
            log.debug("reopen of %s failed: %s", self.config.camera, exc)
            return False
        if self.config.kind.live:
            log.warning("camera %s is back", self.config.camera)
        return True

    def _wait_for_free_slot(self) -> None:
        """Recorded input: wait for the pipeline, so that every frame is processed."""
        with self._cond:
            while self._slot is not None and not self._stop.is_set():
                self._cond.wait(0.1)

    def _publish(self, frame: Frame) -> None:
        with self._cond:
            if self.config.kind.live:
                if self._slot is not None:
                    self.drops += 1
            self._slot = frame
            self.grabbed += 1
            self._cond.notify_all()
