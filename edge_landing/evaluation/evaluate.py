"""Running models over a scene and scoring them with the paper's metrics (the engine behind ``edge-eval``).

Predictions come from :meth:`OnnxModel.predict` (the same code ``edge-run`` uses), resized to the ground
truth's size. Per model: depth raw, per-image median-scaled (the paper's starred rows) and, given a
per-scene scale, calibrated; SSIM and Median Rel of the raw depth; HVO per class against the rest::

    result = evaluate_scene([OnnxModel.load("m.onnx")], Scene("scene/"), EvalConfig(max_depth_m=80.0))
    result["models"][0]["depth"]["raw"]["abs_rel"]
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Dict, Iterable, List, Optional, Sequence

import numpy as np

from edge_landing.evaluation.landable import LandableAccumulator
from edge_landing.evaluation.metrics import (
    Averaging,
    DepthAccumulator,
    HvoAccumulator,
    MeanAccumulator,
    median_rel,
    median_scale,
    ssim,
    valid_mask,
)
from edge_landing.evaluation.scene import Scene
from edge_landing.runtime.core.camera import Attitude
from edge_landing.runtime.core.errors import InputError, SceneError
from edge_landing.runtime.core.labels import HVO_CLASSES
from edge_landing.runtime.core.messages import Prediction
from edge_landing.runtime.perception.inference import OnnxModel


def progress(iterable: Iterable, total: Optional[int] = None, desc: str = "", unit: str = "frame"):
    """A tqdm progress bar on stderr when tqdm is installed (it is an extra), the bare iterable otherwise."""
    try:
        from tqdm import tqdm
    except ImportError:
        return iterable
    return tqdm(iterable, total=total, desc=desc, unit=unit, dynamic_ncols=True)


@dataclass(frozen=True)
class EvalConfig:
    """``min_depth_m``/``max_depth_m``: the valid ground-truth range and the prediction clamp.
    ``depth_averaging``: per-image mean (AdaBins, default) or global; ``hvo_averaging``: global counts
    (default) or per-image mean. ``max_frames``: evaluate only the first N frames (None = all)."""

    min_depth_m: float = 1e-3
    max_depth_m: float = 80.0
    depth_averaging: Averaging = Averaging.PER_IMAGE
    hvo_averaging: Averaging = Averaging.GLOBAL
    max_frames: Optional[int] = None

    def __post_init__(self):
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise InputError(f"need 0 < --min-depth < --max-depth, got {self.min_depth_m} and {self.max_depth_m}")
        if self.max_frames is not None and self.max_frames < 1:
            raise InputError(f"--max-frames must be at least 1, got {self.max_frames}")

    def to_json(self) -> dict:
        d = asdict(self)
        d.update(depth_averaging=self.depth_averaging.value, hvo_averaging=self.hvo_averaging.value)
        return d


def hvo_labels(hvo_prob: np.ndarray) -> np.ndarray:
    """uint8 H×W argmax labels 0/1/2 from H×W×3 probabilities."""
    return np.asarray(hvo_prob).argmax(axis=2).astype(np.uint8)


class ModelScore:
    """The accumulators of one model over one scene."""

    def __init__(self, model: OnnxModel, scene: Scene, config: EvalConfig, scale: Optional[float] = None,
                 calibration_file: Optional[str] = None):
        self.model, self.config, self.scale, self.calibration_file = model, config, scale, calibration_file
        task = model.contract.task
        self.do_depth = task.has_depth and scene.has_depth
        self.do_hvo = task.has_hvo and scene.has_hvo
        lo, hi, avg = config.min_depth_m, config.max_depth_m, config.depth_averaging
        self.raw = DepthAccumulator(lo, hi, avg)
        self.median_scaled = DepthAccumulator(lo, hi, avg)
        self.calibrated = DepthAccumulator(lo, hi, avg) if scale is not None else None
        self.ssim, self.median_rel = MeanAccumulator(), MeanAccumulator()
        self.ratios: List[float] = []
        self.hvo = HvoAccumulator(config.hvo_averaging)
        # The landing figure needs depth and HVO heads, both ground truths and the frames' attitudes.
        self.do_landable = task.has_depth and task.has_hvo and scene.has_depth and scene.has_hvo
        self.landable = LandableAccumulator()
        self.meta = scene.meta
        self.per_frame: List[dict] = []
        self.invalid_frames: List[str] = []

    def add(self, frame_id: str, gt_depth: Optional[np.ndarray], gt_hvo: Optional[np.ndarray],
            pred: Prediction, attitude: Optional[Attitude] = None) -> None:
        lo, hi = self.config.min_depth_m, self.config.max_depth_m
        rec: dict = {"frame": frame_id}
        if not pred.valid:
            # Scored anyway (non-finite depth is clamped like AdaBins does), but counted and reported.
            self.invalid_frames.append(frame_id)
            rec["invalid"] = pred.reason
        if self.do_depth and gt_depth is not None:
            assert pred.depth_m is not None     # do_depth: the model's contract has a depth head
            rec["raw"] = self.raw.add(gt_depth, pred.depth_m)
            s = median_scale(gt_depth, pred.depth_m, lo, hi)
            rec["median_scale"] = s
            if math.isfinite(s):
                self.ratios.append(s)
                rec["median_scaled"] = self.median_scaled.add(gt_depth, pred.depth_m.astype(np.float64) * s)
            if self.calibrated is not None and self.scale is not None:     # (calibrated exists iff scale does)
                rec["calibrated"] = self.calibrated.add(gt_depth, pred.depth_m.astype(np.float64) * self.scale)
            rec["ssim"] = self.ssim.add(ssim(gt_depth, pred.depth_m, lo, hi))
            rec["median_rel"] = self.median_rel.add(median_rel(gt_depth, pred.depth_m, lo, hi))
        if self.do_hvo and gt_hvo is not None:
            assert pred.hvo_prob is not None    # do_hvo: the model's contract has an HVO head
            m = self.hvo.add(gt_hvo, hvo_labels(pred.hvo_prob))
            rec["hvo"] = {k: m[k] for k in (*HVO_CLASSES, "average", "confusion", "baseline")}
        if self.do_landable and attitude is not None and gt_depth is not None and gt_hvo is not None:
            # the runtime fuses calibrated depth: use the per-scene scale when there is one
            as_run = pred if self.scale is None or pred.depth_m is None else Prediction(
                pred.frame_id, pred.capture_time_s, pred.depth_m * np.float32(self.scale), pred.hvo_prob)
            self.landable.add(as_run, gt_depth, gt_hvo, self.meta.intrinsics, self.meta.mount, attitude)
        self.per_frame.append(rec)

    def result(self) -> dict:
        c = self.model.contract
        out: dict[str, Any] = {"name": self.model.path.stem, "path": str(self.model.path), "sha256": self.model.sha256,
               "arch": c.arch, "task": c.task.value, "invalid_frames": self.invalid_frames,
               "depth": None, "hvo": None, "per_frame": self.per_frame}
        if self.do_depth:
            ratios = np.asarray(self.ratios)
            out["depth"] = {
                "frames": self.raw.count, "frames_without_valid_pixels": self.raw.skipped,
                "raw": self.raw.result(), "median_scaled": self.median_scaled.result(),
                "calibrated": self.calibrated.result() if self.calibrated is not None else None,
                "calibration": ({"file": self.calibration_file, "scale": self.scale}
                                if self.calibrated is not None else None),
                "ssim": self.ssim.result(), "median_rel": self.median_rel.result(),
                "median_scale": ({"median": float(np.median(ratios)), "min": float(ratios.min()),
                                  "max": float(ratios.max())} if ratios.size else None),
            }
        if self.do_hvo:
            out["hvo"] = {"frames": self.hvo.count, **self.hvo.result()}
        out["landable"] = self.landable.result() if self.landable.frames else None
        if out["landable"] is not None:
            out["landable"]["depth"] = "calibrated" if self.scale is not None else "raw"
        return out


def evaluate_scene(models: Sequence[OnnxModel], scene: Scene, config: EvalConfig = EvalConfig(),
                   scales: Optional[Dict[int, float]] = None, calibration_files: Optional[Dict[int, str]] = None,
                   show_progress: bool = True) -> dict:
    """Score every model on every frame. ``scales`` maps a model's index to its per-scene scale.

    Raises SceneError when the scene holds no ground truth any model can be scored against, or when a
    frame's ground truth is missing or does not match its image.
    """
    scales, calibration_files = scales or {}, calibration_files or {}
    scores = [ModelScore(m, scene, config, scales.get(i), calibration_files.get(i)) for i, m in enumerate(models)]
    need_depth = any(s.do_depth for s in scores)
    need_hvo = any(s.do_hvo for s in scores)
    if not (need_depth or need_hvo):
        tasks = ", ".join(sorted({m.contract.task.value for m in models}))
        have = [n for n, ok in (("depth", scene.has_depth), ("hvo", scene.has_hvo)) if ok] or ["no ground truth"]
        raise SceneError(f"nothing to evaluate: the model(s) predict {tasks} but scene {scene.path} has "
                         f"{' and '.join(have)} (expected depth/ and/or hvo/ beside rgb/)")
    frame_ids = scene.frame_ids[: config.max_frames] if config.max_frames else scene.frame_ids
    iterator = progress(frame_ids, total=len(frame_ids), desc="edge-eval") if show_progress else frame_ids
    finite_px = in_range_px = 0
    poses = scene.poses()
    for index, fid in enumerate(iterator):
        rgb = scene.read_rgb(fid)
        gt_depth = scene.read_depth(fid) if need_depth else None
        if gt_depth is not None:
            finite_px += int(np.isfinite(gt_depth).sum())
            in_range_px += int(valid_mask(gt_depth, config.min_depth_m, config.max_depth_m).sum())
        gt_hvo = scene.read_hvo(fid) if need_hvo else None
        hw = rgb.shape[:2]
        for name, gt in (("depth", gt_depth), ("hvo", gt_hvo)):
            if gt is not None and gt.shape != hw:
                raise SceneError(f"frame {fid}: {name} ground truth is {gt.shape[0]}x{gt.shape[1]} but the rgb "
                                 f"image is {hw[0]}x{hw[1]}; expected the same size (ARCHITECTURE.md §4)")
        pose = poses.get(fid)
        attitude = Attitude(pose.roll_rad, pose.pitch_rad, pose.yaw_rad) if pose is not None else None
        for model, score in zip(models, scores):
            if score.do_depth or score.do_hvo:
                score.add(fid, gt_depth, gt_hvo, model.predict(rgb, frame_id=index, out_hw=hw), attitude)
    return {"scene": str(scene.path), "frames": len(frame_ids), "config": config.to_json(),
            "depth_pixels": {"finite": finite_px, "in_range": in_range_px} if need_depth else None,
            "models": [s.result() for s in scores]}


# -- qualitative figure -----------------------------------------------------------------------------------
HVO_COLOURS_RGB = {0: (60, 200, 60), 1: (220, 60, 60), 2: (70, 110, 230)}   # horizontal, vertical, other


def colourise_depth(depth_m: np.ndarray, lo_m: float, hi_m: float) -> np.ndarray:
    """RGB uint8 rendering (near = bright) on a log scale from ``lo_m`` to ``hi_m``, NaN black; every map
    of one row shares the range so that colours compare."""
    import cv2

    d = np.asarray(depth_m, dtype=np.float32)
    lo, hi = math.log(max(lo_m, 1e-3)), math.log(max(hi_m, lo_m * 1.01, 1e-3))
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (np.log(np.clip(np.nan_to_num(d, nan=hi_m), 1e-3, None)) - lo) / max(hi - lo, 1e-6)
    scaled = np.clip(1.0 - t, 0, 1)
    rgb = cv2.cvtColor(cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_MAGMA), cv2.COLOR_BGR2RGB)
    rgb[~np.isfinite(d)] = 0
    return rgb


def colourise_hvo(labels: np.ndarray) -> np.ndarray:
    out = np.zeros((*labels.shape, 3), np.uint8)
    for k, colour in HVO_COLOURS_RGB.items():
        out[labels == k] = colour
    return out


def qualitative_grid(models: Sequence[OnnxModel], scene: Scene, frame_ids: Sequence[str],
                     tile_width: int = 240) -> np.ndarray:
    """RGB uint8 grid: one row per frame; columns RGB, ground truth depth and HVO, then each model's
    depth and HVO (columns a model or the scene lacks are left out)."""
    import cv2

    header, rows = None, []
    for fid in frame_ids:
        rgb = scene.read_rgb(fid)
        hw = rgb.shape[:2]
        gt_depth = scene.read_depth(fid) if scene.has_depth else None
        finite = gt_depth[np.isfinite(gt_depth)] if gt_depth is not None else np.empty(0)
        tiles = [("RGB", rgb)]
        preds = [(m.path.stem, m.predict(rgb, out_hw=hw)) for m in models]
        if not finite.size:      # no ground truth: the predictions set the colour range
            finite = np.concatenate([p.depth_m[np.isfinite(p.depth_m)].ravel() for _, p in preds
                                     if p.depth_m is not None] or [np.ones(1)])
        lo, hi = (float(v) for v in np.percentile(finite, [1, 99])) if finite.size else (1.0, 2.0)
        if gt_depth is not None:
            tiles.append(("GT depth", colourise_depth(gt_depth, lo, hi)))
        if scene.has_hvo:
            tiles.append(("GT HVO (g=H r=V b=O)", colourise_hvo(scene.read_hvo(fid))))
        for name, p in preds:
            if p.depth_m is not None:
                tiles.append((f"{name} depth", colourise_depth(p.depth_m, lo, hi)))
            if p.hvo_prob is not None:
                tiles.append((f"{name} HVO", colourise_hvo(hvo_labels(p.hvo_prob))))
        tile_h = max(1, round(tile_width * hw[0] / hw[1]))
        row = [cv2.resize(t, (tile_width, tile_h), interpolation=cv2.INTER_NEAREST) for _, t in tiles]
        rows.append(np.concatenate(row, axis=1))
        if header is None:
            header = np.full((22, tile_width * len(tiles), 3), 255, np.uint8)
            for i, (label, _) in enumerate(tiles):
                cv2.putText(header, label[:28], (i * tile_width + 4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                            (0, 0, 0), 1, cv2.LINE_AA)
    if header is None:
        raise InputError("no frames to draw")
    return np.concatenate([header, *rows], axis=0)
