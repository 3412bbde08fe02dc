"""Per-scene median-scale calibration (ARCHITECTURE.md §7), the engine behind ``edge-calibrate``.

For every frame with ground truth, ratio = median(gt) / median(pred) over valid pixels (Monodepth2's median
scaling); the scene's scale is the median of the ratios, with its spread (MAD, min, max, frames used)::

    cal = calibrate_scene(Scene("scene/"), OnnxModel.load("model.onnx"))
    cal.save("scene/calibration.json")          # read back on the drone with load_calibration()
"""
from __future__ import annotations

import datetime
import logging
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from edge_landing.evaluation.evaluate import progress
from edge_landing.evaluation.metrics import median_scale
from edge_landing.evaluation.scene import Scene
from edge_landing.runtime.core.errors import InputError, SceneError
from edge_landing.runtime.perception.calibration_file import SceneCalibration
from edge_landing.runtime.perception.inference import OnnxModel

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CalibrationConfig:
    """``min_depth_m``/``max_depth_m``: the ground truth counted in the ratios (default: the model's
    contract range, ``edge.depth`` min/max, outside which its predictions are clamped and would bias the
    ratio). ``max_frames``: use only the first N frames (None = all)."""

    min_depth_m: Optional[float] = None
    max_depth_m: Optional[float] = None
    max_frames: Optional[int] = None


class SkippedFrames:
    """Frames left out, said one by one for the first few and then counted, so a scene where most frames
    lack ground truth gives a summary instead of a line per frame."""

    said_each = 3

    def __init__(self) -> None:
        self.by_reason: dict[str, list[str]] = {}
        self.count = 0

    def add(self, frame_id: str, reason: str) -> None:
        self.count += 1
        self.by_reason.setdefault(reason, []).append(frame_id)
        if self.count <= self.said_each:
            log.warning("frame %s: %s; frame skipped", frame_id, reason)

    def summarise(self) -> None:
        if self.count <= self.said_each:
            return
        for reason, ids in self.by_reason.items():
            log.warning("%d frame(s) skipped: %s (first %s, last %s)", len(ids), reason, ids[0], ids[-1])


def calibrate_scene(scene: Scene, model: OnnxModel, config: CalibrationConfig = CalibrationConfig(),
                    show_progress: bool = True) -> SceneCalibration:
    """Run ``model`` over every frame and return the scene's median scale (raises SceneError when no frame
    has usable ground truth)."""
    scene.require(depth=True, purpose="depth-scale calibration (edge-calibrate)")
    spec = model.contract.depth
    if spec is None:
        raise InputError(f"model {model.path} has no depth head (edge.task = {model.contract.task}); "
                         f"calibration needs a depth model")
    lo = config.min_depth_m if config.min_depth_m is not None else spec.min_depth
    hi = config.max_depth_m if config.max_depth_m is not None else spec.max_depth
    if not 0 <= lo < hi:
        raise InputError(f"need 0 <= min depth < max depth, got {lo} and {hi}")
    frame_ids = scene.frame_ids[: config.max_frames] if config.max_frames else scene.frame_ids
    ratios: dict[str, float] = {}
    skipped = SkippedFrames()
    iterator = progress(frame_ids, total=len(frame_ids), desc="edge-calibrate") if show_progress else frame_ids
    for index, fid in enumerate(iterator):
        rgb = scene.read_rgb(fid)
        gt = scene.read_depth(fid)
        if gt.shape != rgb.shape[:2]:
            raise SceneError(f"frame {fid}: depth is {gt.shape[0]}x{gt.shape[1]} but the rgb image is "
                             f"{rgb.shape[0]}x{rgb.shape[1]}; expected the same size (ARCHITECTURE.md §4)")
        pred = model.predict(rgb, frame_id=index, out_hw=gt.shape)
        if not pred.valid:
            skipped.add(fid, f"model output invalid ({pred.reason})")
            continue
        assert pred.depth_m is not None     # the contract has a depth head (checked above)
        r = median_scale(gt, pred.depth_m, lo, hi)
        if math.isfinite(r) and r > 0:
            ratios[fid] = r
        else:
            skipped.add(fid, f"no valid ground-truth pixel in ({lo:g}, {hi:g}) m")
    skipped.summarise()
    if not ratios:
        raise SceneError(f"scene {scene.path}: none of its {len(frame_ids)} frames has valid depth ground truth "
                         f"(finite values in ({lo:g}, {hi:g}) m) and a valid prediction; nothing to calibrate")
    values = np.asarray(list(ratios.values()))
    scale = float(np.median(values))
    return SceneCalibration(
        scale=scale, mad=float(np.median(np.abs(values - scale))), min_ratio=float(values.min()),
        max_ratio=float(values.max()), frames_used=len(ratios), frames_total=len(frame_ids),
        model_sha256=model.sha256, model_path=str(model.path.resolve()), scene_path=str(scene.path.resolve()),
        created_utc=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        min_depth_m=lo, max_depth_m=hi if math.isfinite(hi) else None, ratios=ratios)
