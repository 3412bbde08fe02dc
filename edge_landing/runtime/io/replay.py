"""Recorded inputs replayed with the flight's own telemetry (ARCHITECTURE.md §4): a poses.csv (``edge-run
--poses``, one row per frame) or the MAVLink telemetry log the ground station recorded (``edge-run --tlog``).

Both are readers around the video or image folder; the grabber stamps each frame on a monotonic base fixed at
the first one (``sim_time_s``, the frame's time in the recording) and then calls ``feed_telemetry`` with that
stamp, so the telemetry lands on the frame's clock.
"""
from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Any, List, Optional

import numpy as np

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import VehicleState
from edge_landing.runtime.io.flight_record import frame_times_beside
from edge_landing.runtime.io.sources import Reader
from edge_landing.runtime.io.telemetry import TelemetryBuffer
from edge_landing.runtime.io.tlog import TlogConfig, TlogTelemetry

__all__ = ["PoseReplayReader", "TlogReplayReader"]
log = logging.getLogger(__name__)


class PoseReplayReader(Reader):
    """A recorded input replayed with its ground-truth poses (an ``edge-sim --flight`` poses.csv) as telemetry.

    Row k of the file describes frame k of the input; ``last_state`` is that frame's vehicle state, which the
    grabber stamps with the frame's capture time. Frames past the end of the file get no state.
    """

    def __init__(self, inner: Reader, states: List[VehicleState]):
        self.inner, self.states = inner, states
        self.name = inner.name
        self._index = 0

    @staticmethod
    def states_from_csv(path: str) -> List[VehicleState]:
        from edge_landing.runtime.core.camera import Attitude
        from edge_landing.runtime.io.poses import read_poses_csv

        poses = read_poses_csv(path)
        if not poses:
            raise InputError(f"--poses {path} has no rows: a replay needs one pose per frame")
        return [VehicleState(time_s=p.t_s, attitude=Attitude(p.roll_rad, p.pitch_rad, p.yaw_rad),
                             position_ned_m=np.asarray(p.ned_m, dtype=np.float64), agl_m=p.agl_m,
                             agl_source="poses.csv") for p in poses]

    def read(self) -> Optional[np.ndarray]:
        rgb = self.inner.read()
        self.problem = self.inner.problem
        if rgb is not None:
            self.last_state = self.states[self._index] if self._index < len(self.states) else None
            self.sim_time_s = None if self.last_state is None else self.last_state.time_s
            self._index += 1
        return rgb

    def close(self) -> None:
        self.inner.close()


class TlogReplayReader(Reader):
    """A recorded video (or image folder) whose frames are timed against a telemetry log (``TlogTelemetry``).

    ``sim_time_s`` is the frame's time in the video, so the grabber stamps frames on a base fixed at the first
    one; ``feed_telemetry`` then hands over the log up to that frame on the same clock."""

    def __init__(self, inner: Reader, config: TlogConfig, fps: float):
        """``fps``: the frame rate to time frames by when the recording has none of its own (an image folder)."""
        import cv2

        self.inner, self.name = inner, inner.name
        # A flight recorder's video carries each frame's capture time beside it: the start and the frames' times.
        self._recorded = frame_times_beside(inner.name)
        if self._recorded and not config.video_start:
            config = replace(config, video_start=f"{self._recorded[0]:.6f}")
        self.tlog = TlogTelemetry(config)
        self._cap, self._pos = getattr(inner, "cap", None), cv2.CAP_PROP_POS_MSEC
        container_fps = float(self._cap.get(cv2.CAP_PROP_FPS) or 0.0) if self._cap is not None else 0.0
        self.fps = container_fps if math.isfinite(container_fps) and container_fps > 0 else fps
        self._fault_said = False
        if not self.fps > 0:
            self.tlog.close()
            raise InputError(f"--tlog: the frame rate of {inner.name} is unknown, so its frames cannot be timed; "
                             f"pass --fps")
        self._index = 0
        self._last_pts_s = -math.inf

    def read(self) -> Any:
        rgb = self.inner.read()
        self.problem = self.inner.problem
        if rgb is not None:
            self.sim_time_s = self._pts_s()
            self._index += 1
        return rgb

    def _pts_s(self) -> float:
        """The frame's time in the video: as the flight recorder wrote it beside the video, else the video's own
        time stamp where the container has one, else index / fps."""
        if self._recorded and self._index < len(self._recorded):
            self._last_pts_s = self._recorded[self._index] - self._recorded[0]
            return self._last_pts_s
        pts = self._cap.get(self._pos) / 1000.0 if self._cap is not None else math.nan
        if not (math.isfinite(pts) and pts > self._last_pts_s and (pts > 0 or self._index == 0)):
            pts = self._index / self.fps
        self._last_pts_s = pts
        return pts

    def feed_telemetry(self, telemetry: TelemetryBuffer, capture_time_s: float) -> None:
        """The log up to this frame's time (+ lookahead), its arrival times moved onto the frame's clock."""
        if self.sim_time_s is None:
            return
        frame_unix_s = self.tlog.video_start_unix_s + self.sim_time_s
        try:
            self.tlog.feed_until(telemetry, frame_unix_s + self.tlog.config.lookahead_s, capture_time_s - frame_unix_s)
        except Exception as exc:   # a packet the dialect cannot describe must not stop the grabber: no telemetry
            if not self._fault_said:
                self._fault_said = True
                log.warning("--tlog: a packet could not be read as telemetry (%s); it is skipped", exc)

    def close(self) -> None:
        self.tlog.close()
        self.inner.close()
