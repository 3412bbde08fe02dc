"""The pipeline's per-frame stages before fusion: frame checks, inference, metric scale (ARCHITECTURE.md §6, §7, §10).

Per-frame code never raises: a bad frame or a model fault becomes an invalid prediction with a reason.
"""
from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import List, Optional, Tuple

import numpy as np

from edge_landing.runtime.core.camera import Intrinsics, Mount
from edge_landing.runtime.core.errors import ContractError
from edge_landing.runtime.core.messages import Frame, Prediction, VehicleState
from edge_landing.runtime.perception.inference import OnnxModel
from edge_landing.runtime.perception.scale import AltitudeScaleEstimator

log = logging.getLogger(__name__)
ASPECT_TOLERANCE = 0.01


def _require_head(model: OnnxModel, head: str, role: str) -> None:
    """Fail at start-up, not on every frame: landing needs metric depth, and an HVO model needs its head."""
    task = model.contract.task
    if not (task.has_depth if head == "depth" else task.has_hvo):
        raise ContractError(f"{role} {model.path} has no {head} head (edge.task = {task.value}); edge-run needs "
                            f"a depth+hvo model, or --depth-model with a depth head and --hvo-model with an HVO head")


def invalid(frame: Frame, reason: str) -> Prediction:
    return Prediction(frame.frame_id, frame.capture_time_s, None, None, False, reason)


class JointInference:
    """One model with both heads (or a single head)."""

    def __init__(self, model: OnnxModel):
        _require_head(model, "depth", "the model")
        self.model = model
        self.name = model.path.name

    @property
    def models(self) -> List[OnnxModel]:
        return [self.model]

    def predict(self, frame: Frame) -> Prediction:
        try:
            return self.model.predict(frame.rgb, frame.frame_id, frame.capture_time_s)
        except Exception as exc:  # a model fault marks the frame invalid; it never stops the loop
            return invalid(frame, f"model fault: {exc}")


class PairInference:
    """A depth model and an HVO model run one after the other; HVO is resampled to the depth grid."""

    def __init__(self, depth_model: OnnxModel, hvo_model: OnnxModel):
        _require_head(depth_model, "depth", "the depth model")
        _require_head(hvo_model, "hvo", "the HVO model")
        self.depth_model, self.hvo_model = depth_model, hvo_model
        self.name = f"{depth_model.path.name} + {hvo_model.path.name}"

    @property
    def models(self) -> List[OnnxModel]:
        return [self.depth_model, self.hvo_model]

    def predict(self, frame: Frame) -> Prediction:
        try:
            d = self.depth_model.predict(frame.rgb, frame.frame_id, frame.capture_time_s)
            h = self.hvo_model.predict(frame.rgb, frame.frame_id, frame.capture_time_s,
                                       out_hw=None if d.depth_m is None else d.depth_m.shape)
        except Exception as exc:
            return invalid(frame, f"model fault: {exc}")
        timings = {k: d.timings_s.get(k, 0.0) + h.timings_s.get(k, 0.0) for k in d.timings_s}
        return Prediction(frame.frame_id, frame.capture_time_s, d.depth_m, h.hvo_prob, d.valid and h.valid,
                          d.reason or h.reason, 1.0, timings)


class FrameCheck:
    """Frames whose size changed mid-stream: the same aspect ratio is rescaled (and said once), another is invalid.

    Intrinsics are per image size (ARCHITECTURE.md §3); fusion and scale rescale them to each frame's size,
    which is right only when the camera scaled the whole image, i.e. kept its aspect ratio.
    """

    def __init__(self, width: int, height: int):
        self.width, self.height = width, height
        self._said: Optional[Tuple[int, int]] = None

    def check(self, frame: Frame) -> str:
        """'' when the frame is usable, else why not."""
        if not frame.valid:
            return f"invalid frame: {frame.reason}"
        rgb = frame.rgb
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.size == 0:
            return f"invalid frame: expected H×W×3, got shape {rgb.shape}"
        h, w = rgb.shape[:2]
        if (w, h) == (self.width, self.height):
            return ""
        if abs(w / h - self.width / self.height) > ASPECT_TOLERANCE * self.width / self.height:
            return (f"invalid frame: size changed from {self.width}x{self.height} to {w}x{h} (another aspect ratio; "
                    f"the intrinsics do not apply)")
        if self._said != (w, h):
            log.warning("frame size changed from %dx%d to %dx%d (same aspect ratio): intrinsics rescaled",
                        self.width, self.height, w, h)
            self._said = (w, h)
        return ""


class ScaleStage:
    """Metric scale: the in-flight altitude estimate when it is valid, else the scene calibration, else 1.

    ``require_metric`` (a link is configured and no scene calibration was given): without a valid altitude
    estimate (height above ground unknown or implausible) there is no metric scale, so the prediction
    becomes invalid and no target follows (ARCHITECTURE.md §12).
    """

    def __init__(self, calibration_scale: Optional[float] = None, estimator: Optional[AltitudeScaleEstimator] = None,
                 intrinsics: Optional[Intrinsics] = None, mount: Optional[Mount] = None, require_metric: bool = False):
        self.calibration_scale = calibration_scale
        self.estimator = estimator
        self.intrinsics, self.mount = intrinsics, mount
        self.require_metric = require_metric and not calibration_scale
        self.source = "calibration" if calibration_scale else "none"
        self.last_reason = ""

    def apply(self, pred: Prediction, state: Optional[VehicleState]) -> Prediction:
        if not pred.valid or pred.depth_m is None:
            return pred
        scale, source = self.calibration_scale or 1.0, "calibration" if self.calibration_scale else "none"
        why = "no height above ground" if state is None or state.agl_m is None else ""
        if self.estimator is not None and self.intrinsics is not None and self.mount is not None and not why:
            assert state is not None and state.agl_m is not None
            h, w = pred.depth_m.shape
            est = self.estimator.update(pred.depth_m, pred.hvo_prob, self.intrinsics.scaled(w, h), state.mount_of(self.mount),
                                        state.attitude, state.agl_m)
            self.last_reason = why = est.reason
            if est.valid and math.isfinite(est.scale) and est.scale > 0:
                scale, source, why = float(est.scale), f"altitude ({state.agl_source})", ""
        elif self.estimator is None:
            why = why or "altitude scale is off"
        self.source = source
        if self.require_metric and not source.startswith("altitude"):
            return replace(pred, valid=False, reason=f"no metric scale: {why or 'no altitude estimate'} "
                                                     f"(and no --calibration)")
        if scale == 1.0:
            return pred
        return replace(pred, depth_m=pred.depth_m * np.float32(scale), scale=pred.scale * scale)
