"""Typed handoffs between the pipeline's stages (ARCHITECTURE.md §2): what each stage needs of the next.

The concrete classes live in runtime/io (Grabber, TelemetryBuffer, MavlinkLink, OverlayRecorder) and
runtime/perception; the pipeline only knows these protocols.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Protocol, Tuple

import numpy as np

from edge_landing.runtime.core.messages import Frame, Prediction, Target, TelemetryMatch, VehicleState
from edge_landing.runtime.fusion.grid import GridView
from edge_landing.runtime.fusion.motion_grid import GeometryView
from edge_landing.runtime.fusion.result import FusionResult


class FrameSource(Protocol):
    """Frames in capture order; ``next`` returns None after ``timeout_s`` or at the end (then ``ended``)."""

    @property
    def ended(self) -> bool: ...

    @property
    def drops(self) -> int: ...

    @property
    def faults(self) -> int: ...

    def next(self, timeout_s: float = 1.0) -> Optional[Frame]: ...


class TelemetrySource(Protocol):
    """Vehicle state at a capture time, with the trust rules applied (ARCHITECTURE.md §12)."""

    def lookup(self, capture_time_s: float, now_s: Optional[float] = None) -> TelemetryMatch: ...

    def last_arrival_s(self) -> float: ...

    def newest_state(self) -> Optional[VehicleState]: ...

    def rejected(self) -> Dict[str, int]: ...

    def rates_refused(self) -> Dict[str, int]: ...

    @property
    def samples(self) -> int: ...


class TargetSink(Protocol):
    """Where targets go (the MAVLink link); ``send_target`` says whether the target really left, and why not."""

    @property
    def up(self) -> bool: ...

    def send_target(self, target: Target, state: Optional[VehicleState],
                    clock_lag_s: float = 0.0, stamp_s: Optional[float] = None) -> Tuple[bool, str]: ...

    def send_status(self, text: str, severity: int = 6) -> bool: ...

    def counters(self) -> Dict[str, int]: ...

    def setup_report(self) -> Optional[Dict[str, object]]: ...


class Recorder(Protocol):
    """The overlay video (or anything that wants every frame with its outcome)."""

    def write(self, frame: Frame, pred: Prediction, target: Target, state: Optional[VehicleState] = None,
              grid: Optional[GridView] = None, geometry: Optional[GeometryView] = None) -> None: ...


class Inference(Protocol):
    name: str

    def predict(self, frame: Frame) -> Prediction: ...


class Fuse(Protocol):
    def __call__(self, pred: Prediction, state: Optional[VehicleState], now_s: float,
                 image: Optional[np.ndarray] = None) -> FusionResult: ...


@dataclass(frozen=True)
class FrameWork:
    """One frame on its way from inference to the link (handed to the fusion worker thread)."""

    frame: Frame
    telemetry: TelemetryMatch
    pred: Prediction
    started_s: float  # perf_counter() when the frame's processing began
