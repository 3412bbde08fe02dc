"""The accuracy guard of edge-quantize: INT8 against FP32 on held-out frames, and the tolerance.

Depth: δ1 and AbsRel against ground truth (or against FP32 without it) and the share of pixels within 5 %
of FP32; HVO: mean IoU, precision of 'horizontal' (what landing relies on) and the share of pixels where
both pick the same class. Example::

    comparison = compare(fp32_model, int8_model, [(scene, "000016"), (scene, "000017")])
    reasons = check_tolerance(comparison, Tolerance())      # [] when INT8 is good enough
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, List, Sequence, Tuple

import numpy as np

from edge_landing.evaluation.metrics import DepthAccumulator, HvoAccumulator
from edge_landing.evaluation.scene import Scene
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.perception.inference import OnnxModel

FrameRef = Tuple[Scene, str]     # one frame: its scene and its id


def frame_label(ref: FrameRef) -> str:
    return f"{ref[0].path.name}/{ref[1]}"


@dataclass(frozen=True)
class Tolerance:
    """How much INT8 may lose against FP32 on the held-out frames (absolute changes, shares in [0, 1])."""

    max_delta1_drop: float = 0.02        # depth δ1 vs ground truth (or vs FP32 without ground truth)
    max_abs_rel_increase: float = 0.02   # depth AbsRel
    min_depth_agreement: float = 0.90    # share of pixels where INT8 depth is within 5 % of FP32
    max_miou_drop: float = 0.02          # HVO mean IoU over the three classes
    max_hprec_drop: float = 0.02         # HVO precision of 'horizontal' (what landing relies on)
    min_label_agreement: float = 0.90    # share of pixels where INT8 and FP32 pick the same HVO class

    def __post_init__(self) -> None:
        # A NaN tolerance would pass every comparison and switch the accuracy gate off without a word.
        for flag, value in (("--max-delta1-drop", self.max_delta1_drop), ("--max-absrel-increase",
                            self.max_abs_rel_increase), ("--min-depth-agreement", self.min_depth_agreement),
                            ("--max-miou-drop", self.max_miou_drop), ("--max-hprec-drop", self.max_hprec_drop),
                            ("--min-label-agreement", self.min_label_agreement)):
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise InputError(f"{flag} must be between 0 and 1, got {value}")


def _has_ground_truth(frames: Sequence[FrameRef], folder: str, suffix: str) -> bool:
    """Every held-out frame has this ground truth (a scene writer may leave an empty depth/ or hvo/ folder)."""
    return all((scene.path / folder / f"{fid}{suffix}").exists() for scene, fid in frames)


def compare(fp32: OnnxModel, int8: OnnxModel, frames: Sequence[FrameRef], progress: bool = True) -> dict:
    """INT8 against FP32 on held-out frames: metrics vs ground truth (or vs FP32 without it) and agreement."""
    from tqdm import tqdm

    c = fp32.contract
    use_gt_depth = c.depth is not None and _has_ground_truth(frames, "depth", ".npy")
    use_gt_hvo = c.hvo is not None and _has_ground_truth(frames, "hvo", ".png")
    lo, hi = (c.depth.min_depth, c.depth.max_depth) if c.depth is not None else (0.0, 0.0)
    depth_acc = {k: DepthAccumulator(lo, hi) for k in ("fp32", "int8")} if c.depth is not None else None
    # INT8 against FP32 as well: the fall-back when no ground-truth pixel lies inside the model's depth range
    # (a NYU model, 10 m at most, over a drone scene 30-300 m away)
    vs_fp32 = DepthAccumulator(lo, hi) if c.depth is not None else None
    hvo_acc = {k: HvoAccumulator() for k in ("fp32", "int8")} if c.hvo is not None else None
    depth_agree, label_agree = [], []
    for scene, fid in tqdm(frames, desc="comparing INT8 with FP32", unit="frame", disable=not progress, leave=False):
        rgb = scene.read_rgb(fid)
        gt_d = scene.read_depth(fid) if use_gt_depth else None
        gt_h = scene.read_hvo(fid) if use_gt_hvo else None
        out_hw = (gt_d.shape if gt_d is not None else gt_h.shape if gt_h is not None else rgb.shape[:2])
        p32, p8 = fp32.predict(rgb, out_hw=tuple(out_hw)), int8.predict(rgb, out_hw=tuple(out_hw))
        if depth_acc is not None:
            # A model whose contract has a depth head predicts depth on every frame.
            assert vs_fp32 is not None and p32.depth_m is not None and p8.depth_m is not None
            ref = gt_d if gt_d is not None else p32.depth_m
            depth_acc["fp32"].add(ref, p32.depth_m)
            depth_acc["int8"].add(ref, p8.depth_m)
            vs_fp32.add(p32.depth_m, p8.depth_m)
            with np.errstate(invalid="ignore", divide="ignore"):
                ratio = np.abs(p8.depth_m / p32.depth_m - 1.0)
            depth_agree.append(float(np.mean(np.nan_to_num(ratio, nan=1.0) < 0.05)))
        if hvo_acc is not None:
            assert p32.hvo_prob is not None and p8.hvo_prob is not None   # the contract has an HVO head
            l32, l8 = p32.hvo_prob.argmax(axis=2), p8.hvo_prob.argmax(axis=2)
            ref = gt_h if gt_h is not None else l32
            hvo_acc["fp32"].add(ref, l32)
            hvo_acc["int8"].add(ref, l8)
            label_agree.append(float(np.mean(l32 == l8)))
    result: dict = {"frames": len(frames), "first": frame_label(frames[0]), "last": frame_label(frames[-1])}
    if depth_acc is not None:
        m: dict[str, dict[str, Any]] = {k: acc.result() for k, acc in depth_acc.items()}
        reference = "ground truth" if use_gt_depth else "fp32"
        if use_gt_depth and depth_acc["fp32"].count == 0:
            assert vs_fp32 is not None
            m = {"fp32": {"a1": 1.0, "abs_rel": 0.0}, "int8": vs_fp32.result()}
            reference = f"fp32 (no ground-truth pixel inside the model's {lo:g}-{hi:g} m range)"
        result["depth"] = {"reference": reference,
                           "fp32": {"a1": m["fp32"]["a1"], "abs_rel": m["fp32"]["abs_rel"]},
                           "int8": {"a1": m["int8"]["a1"], "abs_rel": m["int8"]["abs_rel"]},
                           "delta1_drop": m["fp32"]["a1"] - m["int8"]["a1"],
                           "abs_rel_increase": m["int8"]["abs_rel"] - m["fp32"]["abs_rel"],
                           "agreement": float(np.mean(depth_agree))}
    if hvo_acc is not None:
        m = {k: acc.result() for k, acc in hvo_acc.items()}
        pick = {k: {"miou": v["average"]["iou"], "horizontal_precision": v["horizontal"]["precision"]}
                for k, v in m.items()}
        result["hvo"] = {"reference": "ground truth" if use_gt_hvo else "fp32", **pick,
                         "miou_drop": pick["fp32"]["miou"] - pick["int8"]["miou"],
                         "hprec_drop": pick["fp32"]["horizontal_precision"] - pick["int8"]["horizontal_precision"],
                         "agreement": float(np.mean(label_agree))}
    return result


def check_tolerance(comparison: dict, tol: Tolerance) -> List[str]:
    """Reasons the INT8 model fails the tolerance (empty when it passes). NaN figures count as failures
    only for agreement, since a metric can be NaN for both models (e.g. a class absent from the frames)."""
    reasons = []

    def over(value: float, limit: float, what: str) -> None:
        if np.isfinite(value) and value > limit:
            reasons.append(f"{what} {value:+.4f} exceeds {limit:.4f}")

    def under(value: float, limit: float, what: str) -> None:
        if not (np.isfinite(value) and value >= limit):
            reasons.append(f"{what} {value:.4f} below {limit:.4f}")

    if "depth" in comparison:
        d = comparison["depth"]
        over(d["delta1_drop"], tol.max_delta1_drop, "depth δ1 drop")
        over(d["abs_rel_increase"], tol.max_abs_rel_increase, "depth AbsRel increase")
        under(d["agreement"], tol.min_depth_agreement, "depth agreement with FP32 (within 5 %)")
    if "hvo" in comparison:
        h = comparison["hvo"]
        over(h["miou_drop"], tol.max_miou_drop, "HVO mIoU drop")
        over(h["hprec_drop"], tol.max_hprec_drop, "HVO horizontal-precision drop")
        under(h["agreement"], tol.min_label_agreement, "HVO label agreement with FP32")
    return reasons
