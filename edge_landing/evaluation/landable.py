"""Landable precision: of the pixels the runtime would call landable, the share that truly are.

"Called landable" uses the runtime's own decision rule, not a copy of it: the prediction goes through
:class:`LandingFuser` (FusionConfig defaults, the frame's attitude from poses.csv, vehicle-centred grid), and
a pixel is called landable when its *predicted* point (predicted depth along its ray, at the fuser's
working size) falls in a cell the fuser judged landable. "Truly landable" runs the same fuser on the ground
truth (ground-truth depth, one-hot ground-truth labels) and takes the pixel's *true* point: a pixel counts
when it lies in a cell landable by the truth. So a pixel the net places on the right spot but on a wall,
or on a roof edge it sees as flat, is a false call. The base rate is the share of labelled pixels that
are truly landable (the precision of calling everything landable).

Pure numpy/OpenCV (the fuser is); frames without a pose are skipped by the caller.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount, ned_from_camera
from edge_landing.runtime.core.labels import HVO_IGNORE
from edge_landing.runtime.core.messages import Prediction, VehicleState
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
from edge_landing.runtime.fusion.grid import GridView

HORIZONTAL = 0


def _cells_landable(view: Optional[GridView], north_m: np.ndarray, east_m: np.ndarray) -> np.ndarray:
    """Bool per point: inside ``view`` and in a landable cell (False outside the grid or without a grid)."""
    out = np.zeros(north_m.shape, dtype=bool)
    if view is None:
        return out
    with np.errstate(invalid="ignore"):
        r = np.floor((north_m - view.north0_m) / view.cell_m)
        c = np.floor((east_m - view.east0_m) / view.cell_m)
        rows, cols = view.shape
        inside = np.isfinite(r) & np.isfinite(c) & (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
    out[inside] = view.landable[r[inside].astype(np.int64), c[inside].astype(np.int64)]
    return out


def _level_points(depth_m: np.ndarray, intrinsics: Intrinsics, r_nc: np.ndarray) -> np.ndarray:
    """H×W×3 points in the level vehicle frame (north, east, down; origin at the camera)."""
    rays = intrinsics.pixel_rays().astype(np.float64)
    return (rays @ r_nc.T) * depth_m[..., None]


def _at(a: np.ndarray, hw: tuple[int, int], interpolation: int) -> np.ndarray:
    if a.shape[:2] == hw:
        return a
    return cv2.resize(a, (hw[1], hw[0]), interpolation=interpolation)


@dataclass
class LandableAccumulator:
    """Pixel counts over frames: labelled, truly landable, called landable, called and truly landable."""

    config: FusionConfig = FusionConfig()
    labelled: int = 0
    truly: int = 0
    called: int = 0
    hits: int = 0
    frames: int = 0

    def add(self, pred: Prediction, gt_depth_m: np.ndarray, gt_hvo: np.ndarray, intrinsics: Intrinsics,
            mount: Mount, attitude: Attitude) -> None:
        hw = self.config.working_hw
        state = VehicleState(time_s=0.0, attitude=attitude)
        one_hot = np.zeros((*gt_hvo.shape, 3), np.float32)
        for k in range(3):
            one_hot[..., k] = gt_hvo == k
        depth_t = np.where(np.isfinite(gt_depth_m), gt_depth_m, np.nan).astype(np.float32)
        truth = Prediction(0, 0.0, depth_t, one_hot)
        view_t = LandingFuser(self.config, intrinsics, mount).fuse(truth, state, now_s=0.0).grid
        view_p = None
        if pred.depth_m is not None:
            as_run = Prediction(0, 0.0, pred.depth_m, pred.hvo_prob)
            view_p = LandingFuser(self.config, intrinsics, mount).fuse(as_run, state, now_s=0.0).grid
        small = intrinsics.scaled(hw[1], hw[0])
        r_nc = ned_from_camera(mount, attitude)
        labels = _at(np.asarray(gt_hvo, np.uint8), hw, cv2.INTER_NEAREST)
        labelled = labels != HVO_IGNORE
        pts_t = _level_points(_at(depth_t, hw, cv2.INTER_NEAREST).astype(np.float64), small, r_nc)
        true_l = _cells_landable(view_t, pts_t[..., 0], pts_t[..., 1]) & labelled
        called = np.zeros(hw, dtype=bool)
        if view_p is not None and pred.depth_m is not None:
            d = np.asarray(pred.depth_m, np.float32)
            with np.errstate(invalid="ignore"):
                d = np.where(np.isfinite(d) & (d > 0), d, np.nan).astype(np.float32)
            pts_p = _level_points(_at(d, hw, cv2.INTER_LINEAR).astype(np.float64), small, r_nc)
            called = _cells_landable(view_p, pts_p[..., 0], pts_p[..., 1]) & labelled
        self.labelled += int(labelled.sum())
        self.truly += int(true_l.sum())
        self.called += int(called.sum())
        self.hits += int((called & true_l).sum())
        self.frames += 1

    def result(self) -> dict:
        def ratio(a: int, b: int) -> float:
            return a / b if b else math.nan

        precision, base = ratio(self.hits, self.called), ratio(self.truly, self.labelled)
        return {"frames": self.frames, "landable_precision": precision, "landable_base_rate": base,
                "landable_lift": precision - base if self.called and self.labelled else math.nan,
                "landable_recall": ratio(self.hits, self.truly), "called_share": ratio(self.called, self.labelled),
                "rule": "runtime LandingFuser (FusionConfig defaults, vehicle grid) on the prediction vs on the "
                        "ground truth; pixels at the fuser's working size"}
