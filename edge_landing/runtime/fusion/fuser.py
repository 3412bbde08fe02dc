"""Fusion: metric depth + HVO probabilities -> one landing target per frame (ARCHITECTURE.md §6).

Per frame: resize to the working size, smooth the depth a little (pixel noise would read as slope),
back-project, rotate into a gravity-aligned frame (mount and attitude at capture), slope from the depth's
own normals, rasterise into a top-down grid (edge_landing.runtime.fusion.grid), clearance by distance transform, then
pick the spot (edge_landing.runtime.fusion.landing) and express it for the autopilot.
Pure numpy/OpenCV; ``update`` never raises: every failure is a ``Target.none(..., reason)``.

    fuser = LandingFuser(FusionConfig(), Intrinsics.from_hfov(640, 480), Mount())
    target = fuser.update(prediction, state, now_s=time.monotonic())
    if target.valid: send(target.position_body_frd_m)
    overlay(fuser.grid.landable, fuser.grid.clearance_m)

Frames: without a vehicle position the grid is rebuilt each frame around the vehicle in the level frame
(NED-oriented, origin at the camera). With ``state.position_ned_m`` it is kept in local NED across frames,
its evidence decaying with ``decay_s``, so the target stays put in the world while the vehicle moves. Each
cell is judged within its frame (network depth scale wanders ~1 % between frames, more than the 0.1 m
spread limit at 40-80 m) and only the verdicts are accumulated: a cell is landable while at least
``min_vote_share`` of its decayed observations found it landable (edge_landing.runtime.fusion.grid.TopDownGrid), so an
obstacle that appears on a cell seen clear for long outvotes it after decay_s·ln(1/min_vote_share) (~1 s).
Depth is required. HVO is optional: without it (a depth-only model) cells are judged by the depth slope and
height spread alone and the confidence is multiplied by ``depth_only_confidence`` (degraded mode, said in
the target's ``reason``).

The network may propose, only geometry may confirm (ARCHITECTURE.md §11): with the camera image, the
vehicle position and its height above ground, fusion.confirm runs the motion stage (fusion.motion) and
keeps per-cell evidence in NED (fusion.motion_grid). Settings: fusion.config. A spot is sent only when
its clear disc is landable by the network *and* geometry-clear (measured to ``obstacle_height_m`` within
``geometry_memory_s``, nothing seen standing out). Before that the network's spot is tracked
(``Target.tracked_ned_m``) but the target is not valid, and says why; ``allow_unconfirmed`` sends it anyway
(offline single images have no motion), marked ``evidence="network only"``.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import replace
from functools import partial
from typing import Optional

import cv2
import numpy as np

from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount, ned_from_camera
from edge_landing.runtime.core.messages import EVIDENCE_NETWORK_ONLY, Prediction, Target, VehicleState
from edge_landing.runtime.core.target_frames import aim_from_offset
from edge_landing.runtime.fusion.cells import gather
from edge_landing.runtime.fusion.config import FusionConfig
from edge_landing.runtime.fusion.confirm import GeometryConfirmation
from edge_landing.runtime.fusion.focus import focus_candidates
from edge_landing.runtime.fusion.grid import CellRules, GridView, TopDownGrid
from edge_landing.runtime.fusion.landing import Choice, KeptSpot, choose_spot
from edge_landing.runtime.fusion.motion import ParallaxResult
from edge_landing.runtime.fusion.motion_grid import GeometryView
from edge_landing.runtime.fusion.result import FusionResult
from edge_landing.runtime.fusion.splat import footprint_keys, splat

__all__ = ["DEGRADED_NO_HVO", "FusionConfig", "LandingFuser"]

log = logging.getLogger(__name__)
DEGRADED_NO_HVO = "degraded: depth only (no HVO head), confidence lowered"
_MAX_DEPTH_M = 1.0e4      # far beyond any ground fusion can use (the grid reaches tens of metres)


def _resize(a: np.ndarray, hw: tuple[int, int], interpolation: int) -> np.ndarray:
    if a.shape[:2] == tuple(hw):
        return a
    return cv2.resize(a, (hw[1], hw[0]), interpolation=interpolation)


def _all_within(a: np.ndarray, lo: float, hi: float) -> bool:
    """Whether every value of ``a`` is in [lo, hi]: NaN propagates through min and max, so it fails too."""
    return bool(np.min(a) >= lo and np.max(a) <= hi)


def _smooth_depth(depth: np.ndarray, size: int, max_step: float) -> np.ndarray:
    """Mean of each size×size window, only where the window is all valid and spans no depth step.

    Network depth has pixel-level noise that one-pixel normals would read as slope, so it is averaged
    first. Averaging across an edge would move a thin object's pixels along their rays into mid-air
    ("flying pixels") and lose it (found on sim ground truth: a tree crown 6 m up inside a clear disc), so
    windows whose depth range exceeds ``max_step`` × depth keep the raw value. NaN is handled explicitly:
    a running-sum box filter would carry one NaN along the whole row.
    """
    valid = np.isfinite(depth)
    k = (size, size)
    kernel = np.ones(k, np.uint8)
    if valid.all():                                      # the usual case: no masking needed
        lo = cv2.erode(depth, kernel, borderType=cv2.BORDER_REPLICATE)
        hi = cv2.dilate(depth, kernel, borderType=cv2.BORDER_REPLICATE)
        mean = cv2.blur(depth, k, borderType=cv2.BORDER_REPLICATE)
        return np.where(hi - lo <= max_step * depth, mean, depth)
    lo = cv2.erode(np.where(valid, depth, np.float32(np.inf)), kernel, borderType=cv2.BORDER_REPLICATE)
    hi = cv2.dilate(np.where(valid, depth, np.float32(0.0)), kernel, borderType=cv2.BORDER_REPLICATE)
    total = cv2.blur(np.where(valid, depth, np.float32(0.0)), k, borderType=cv2.BORDER_REPLICATE)
    share = cv2.blur(valid.astype(np.float32), k, borderType=cv2.BORDER_REPLICATE)
    with np.errstate(invalid="ignore", divide="ignore"):
        smooth = (share > 1.0 - 1e-4) & (hi - lo <= max_step * depth)
        return np.where(smooth, total / share, depth).astype(np.float32)


class LandingFuser:
    """Stateful per-stream fusion; call :meth:`update` once per prediction, in capture order."""

    def __init__(self, config: FusionConfig, intrinsics: Intrinsics, mount: Mount):
        self.config = config
        self.mount = mount
        h, w = config.working_hw
        self.intrinsics = intrinsics.scaled(w, h)
        # Rays as 3×(H·W) rows for one matrix product per frame, and each interior pixel's index in the image.
        self._rays_planar = np.ascontiguousarray(self.intrinsics.pixel_rays().reshape(-1, 3).T)
        interior = np.arange((h - 2) * (w - 2))
        self._interior_to_full = interior + 2 * (interior // (w - 2)) + w + 1
        self._grid = TopDownGrid(config.cell_m, config.grid_radius_m)
        self._view: Optional[GridView] = None
        self._mode: Optional[str] = None
        self._epoch = 0                         # VehicleState.position_epoch the NED grids were built in
        self._last_time_s: Optional[float] = None
        self._kept: Optional[KeptSpot] = None
        self._tracked: Optional[KeptSpot] = None
        self._confirm = GeometryConfirmation(config, intrinsics, mount)
        self.motion = self._confirm.motion

    @property
    def grid(self) -> Optional[GridView]:
        """The grid of the last fused frame (landable mask, clearance map, cell centres), or None."""
        return self._view

    @property
    def geometry(self) -> Optional[GeometryView]:
        """Motion-geometry evidence on the last frame's grid (clear / obstacle cells), or None."""
        return self._confirm.view

    @property
    def stage_result(self) -> Optional[ParallaxResult]:
        """The newest frame pair the motion stage added to the evidence (overlapped: the run an earlier frame
        handed over), or None (none yet, or that run measured nothing)."""
        last = self._confirm.last
        return None if last is None else last.result

    @property
    def stage_reason(self) -> str:
        """Why the newest stage run measured what it did (the stage's ``last_reason``)."""
        last = self._confirm.last
        return "" if last is None else last.reason

    @property
    def geometry_ran(self) -> bool:
        """Whether the last :meth:`update` ran the motion stage (it runs every ``geometry_interval_s``)."""
        return self._confirm.ran

    def reset(self) -> None:
        self._grid.clear()
        self._confirm.reset()
        self._view, self._mode, self._last_time_s, self._kept, self._tracked = None, None, None, None, None

    def fuse(self, pred: Prediction, state: VehicleState | None = None, now_s: float | None = None,
             image: Optional[np.ndarray] = None) -> FusionResult:
        """:meth:`update` plus the grid this frame was judged on (None when the frame did not reach the grid)."""
        before = self._view
        target = self.update(pred, state, now_s, image)
        reached = self._view is not before
        return FusionResult(target, self._view if reached else None, self._confirm.view if reached else None,
                            self._confirm.mount_estimate, self._confirm.placement if reached else None)

    def update(self, pred: Prediction, state: VehicleState | None = None, now_s: float | None = None,
               image: Optional[np.ndarray] = None) -> Target:
        """Fuse one frame. ``image``: the camera frame (RGB or grey uint8, any size) for motion geometry."""
        t0 = time.perf_counter()
        timings = dict(getattr(pred, "timings_s", None) or {})
        self._confirm.begin_frame()        # a frame that stops before geometry did not run the stage
        try:
            target = self._update(pred, state, now_s, timings, image)
        except Exception as exc:  # a flight loop must not die on one frame; the frame gets no target
            log.exception("fusion failed on frame %s", getattr(pred, "frame_id", "?"))
            target = Target.none(getattr(pred, "frame_id", -1), getattr(pred, "capture_time_s", float("nan")),
                                 f"fusion error: {type(exc).__name__}: {exc}", timings)
        target.timings_s["fusion"] = time.perf_counter() - t0
        return target

    # -- the steps -------------------------------------------------------------------------------------

    def _update(self, pred: Prediction, state: Optional[VehicleState], now_s: Optional[float],
                timings: dict[str, float], image: Optional[np.ndarray] = None) -> Target:
        cfg = self.config
        fid, t_cap = pred.frame_id, float(pred.capture_time_s)

        def none(reason: str) -> Target:
            return Target.none(fid, t_cap, reason, timings)

        if not pred.valid:
            return none(f"invalid prediction: {pred.reason or 'no reason given'}")
        if not math.isfinite(t_cap):
            return none("invalid prediction: capture time is not finite")
        if now_s is not None and now_s - t_cap > cfg.stale_after_s:
            return none(f"stale frame: captured {now_s - t_cap:.3f} s ago (limit {cfg.stale_after_s} s)")
        if pred.depth_m is None:
            return none("no depth: fusion needs metric depth and this model has no depth head")
        depth = np.asarray(pred.depth_m)
        if depth.ndim == 3 and depth.shape[2] == 1:
            depth = depth[..., 0]
        if depth.ndim != 2 or depth.size == 0:
            return none(f"invalid prediction: depth must be H×W, got shape {depth.shape}")
        hvo_h = None
        if pred.hvo_prob is not None:
            hvo = np.asarray(pred.hvo_prob)
            if hvo.ndim != 3 or hvo.shape[2] != 3:
                return none(f"invalid prediction: HVO probabilities must be H×W×3, got shape {hvo.shape}")
            hvo_h = _resize(np.ascontiguousarray(hvo[..., 0], dtype=np.float32), cfg.working_hw, cv2.INTER_AREA)
            if not _all_within(hvo_h, 0.0, 1.0):                 # (the usual case needs no pass to fix it)
                hvo_h = np.where(np.isfinite(hvo_h), np.clip(hvo_h, 0.0, 1.0), 0.0)  # unknown = not horizontal

        attitude, position = Attitude(), None
        if state is not None:
            att = state.attitude
            if not all(math.isfinite(v) for v in (att.roll_rad, att.pitch_rad, att.yaw_rad)):
                return none("invalid telemetry: attitude is not finite")
            attitude = att
            if state.position_ned_m is not None:
                position = np.asarray(state.position_ned_m, dtype=np.float64).reshape(-1)
                if position.shape != (3,) or not np.all(np.isfinite(position)):
                    return none(f"invalid telemetry: vehicle position must be 3 finite numbers, got {position}")

        # Invalid (NaN, inf, 0, negative or absurdly far) becomes NaN before resizing so it cannot blend into
        # real depth. The far bound keeps the normals' float32 products finite (1e30 m overflowed them).
        depth = np.asarray(depth, dtype=np.float32)
        if not (np.min(depth) > 0 and np.max(depth) <= _MAX_DEPTH_M):   # (NaN fails both: the usual case skips this)
            with np.errstate(invalid="ignore"):
                depth = np.where((depth > 0) & (depth <= _MAX_DEPTH_M), depth, np.float32(np.nan))
        # Linear, not nearest: it samples the working pixel's centre exactly (nearest is off by half a source
        # pixel, a height bias); NaN spreads to neighbours, which only removes points.
        depth = _resize(depth, cfg.working_hw, cv2.INTER_LINEAR)
        if cfg.depth_smoothing_px > 1:
            depth = _smooth_depth(depth, cfg.depth_smoothing_px, cfg.smoothing_max_step)
        valid_share = float(np.count_nonzero(np.isfinite(depth))) / depth.size
        if valid_share < cfg.min_valid_depth_share:
            return none(f"no usable depth: {100 * valid_share:.1f}% of pixels valid "
                        f"(need {100 * cfg.min_valid_depth_share:.0f}%)")

        mount = state.mount_of(self.mount) if state is not None else self.mount   # a gimbal's, when reported
        r_nc = ned_from_camera(mount, attitude)
        epoch = 0 if state is None else state.position_epoch
        if position is not None and epoch != self._epoch:
            # The autopilot's local frame moved (telemetry.TelemetryBuffer): evidence, keyframes and spots kept
            # in the old frame would be misplaced by the jump, so they are dropped, as after a reset.
            log.warning("vehicle position epoch %d -> %d: fusion and geometry evidence start over", self._epoch, epoch)
            self.reset()
            self._epoch = epoch
        self._prepare_grid(position, t_cap)
        n_in = self._rasterise(depth, hvo_h, r_nc.astype(np.float32), position)
        mode = "ned" if position is not None else "vehicle"
        self._view = self._grid.evaluate(CellRules(cfg.min_points_per_cell, cfg.max_height_spread_m,
                                                   cfg.min_horizontal_share, cfg.min_flat_share,
                                                   use_hvo=hvo_h is not None,
                                                   min_neighbours_to_fill=cfg.min_neighbours_to_fill,
                                                   min_vote_share=cfg.min_vote_share,
                                                   min_seen_weight=math.exp(-cfg.memory_s / cfg.decay_s)), mode)
        if n_in == 0 and mode == "vehicle":
            return none(f"no depth inside the grid: nothing valid within {cfg.grid_radius_m} m of the vehicle")

        here = (0.0, 0.0) if position is None else (float(position[0]), float(position[1]))
        for name in ("_kept", "_tracked"):
            kept = getattr(self, name)
            if kept is not None and t_cap - kept.time_s > cfg.keep_target_s:
                setattr(self, name, None)
        proposal = choose_spot(self._view, here, cfg, self._tracked)
        # With no landable disc of the network's own, the window still goes to ground a confirmation may use.
        focus = partial(focus_candidates, self._view,
                        None if proposal is None else np.array([proposal.north_m, proposal.east_m, proposal.down_m]),
                        here, cfg, known=self._confirm.known_obstacles(), use_hvo=hvo_h is not None)
        t_geo = time.perf_counter()
        geo = self._confirm.run(self._view, image, state, position, t_cap, focus)
        timings["geometry"] = time.perf_counter() - t_geo      # on this frame's path
        if math.isfinite(self._confirm.stage_s):
            timings["geometry_stage"] = self._confirm.stage_s   # the run added this frame (its own thread's time)
        self._tracked = None if proposal is None else KeptSpot(proposal.north_m, proposal.east_m, t_cap)
        confirmed_view = None
        if geo is not None:
            # Geometry-clear ground the network does not object to (fusion.confirm.confirmed_view), with or
            # without a network spot of its own.
            confirmed_view = self._confirm.confirmed_view(self._view, hvo_h is not None)
            choice = choose_spot(confirmed_view, here, cfg, self._kept)
            if choice is not None:
                return self._make_target(pred, choice, (attitude, mount), position, hvo_h is not None, timings,
                                         self._confirm.evidence() + self._confirm.verdict_note(choice, self._view))
        self._kept = None
        if proposal is None:
            best = float(self._view.clearance_m.max())
            return none(f"no safe spot: best clearance {best:.2f} m < required {cfg.required_clearance_m:.2f} m")
        why = self._confirm.unconfirmed_reason(proposal, self._view, confirmed_view)
        if cfg.allow_unconfirmed:
            target = self._make_target(pred, proposal, (attitude, mount), position, hvo_h is not None, timings,
                                       f"{EVIDENCE_NETWORK_ONLY} ({why})")
            self._kept = None              # an unconfirmed spot never becomes the committed one
            return target
        target = none(why)
        point = np.array([proposal.north_m, proposal.east_m, proposal.down_m])
        return replace(target, tracked_ned_m=point if position is not None else None, evidence=EVIDENCE_NETWORK_ONLY)

    def _prepare_grid(self, position: Optional[np.ndarray], t_cap: float) -> None:
        """Fresh grid in vehicle mode; in NED mode decay by elapsed time and move with the vehicle."""
        mode = "ned" if position is not None else "vehicle"
        last = self._last_time_s
        if mode != self._mode or mode == "vehicle" or last is None or t_cap < last:
            self._grid.clear(float(position[2]) if position is not None else 0.0)
            if mode != self._mode or (last is not None and t_cap < last):
                self._kept = None  # a target in the other frame (or from the future) means nothing now
            self._mode = mode
        else:
            self._grid.decay(math.exp(-(t_cap - last) / self.config.decay_s))
        self._grid.centre_on(*((float(position[0]), float(position[1])) if position is not None else (0.0, 0.0)))
        self._last_time_s = t_cap

    def _rasterise(self, depth: np.ndarray, hvo_h: Optional[np.ndarray], r_nc: np.ndarray,
                   position: Optional[np.ndarray]) -> int:
        """Back-project, rotate to the level frame, vote flat/horizontal per pixel and splat into the grid.

        The slope is geometry.normals_from_points' recipe (cross product of central differences), written
        out here because the same differences also give each pixel's footprint, and only the normal's
        vertical share is needed: flat <=> n_z² >= cos²(max_slope)·|n|² (no sqrt, no arccos, no NaN fill).
        tests/test_fusion.py checks that it agrees with geometry.hvo_from_normals.
        """
        cfg = self.config
        # Planar layout (3×H×W): level point = depth · (R @ ray), the ray table undistorted (Intrinsics.pixel_rays).
        h, w = depth.shape
        pts = np.matmul(r_nc, self._rays_planar).reshape(3, h, w)     # level ray directions (one small product)
        pts *= depth[None]                                             # x north, y east, z down
        # Central differences (two-pixel steps): the normal's recipe and each pixel's footprint.
        su = pts[:, 1:-1, 2:] - pts[:, 1:-1, :-2]
        sv = pts[:, 2:, 1:-1] - pts[:, :-2, 1:-1]
        nx = su[1] * sv[2] - su[2] * sv[1]
        ny = su[2] * sv[0] - su[0] * sv[2]
        nz = su[0] * sv[1] - su[1] * sv[0]
        nn = nx * nx + ny * ny + nz * nz                               # NaN next to holes and invalid depth
        reach = cfg.grid_radius_m + cfg.max_footprint_m
        with np.errstate(invalid="ignore"):
            keep = (nn > 0) & (np.abs(pts[0, 1:-1, 1:-1]) <= reach) & (np.abs(pts[1, 1:-1, 1:-1]) <= reach)
        idx = np.flatnonzero(keep)                                     # flat index into the (h-2)×(w-2) interior
        if idx.size == 0:
            return 0
        # Gathers (cells.gather) with integer indices on contiguous arrays: boolean masks on strided views and fancy
        # indexing are several times slower here. Pixels are put in lattice order once (fusion.splat).
        su, sv, pts = su.reshape(3, -1), sv.reshape(3, -1), pts.reshape(3, -1)
        keys = footprint_keys(gather(su[:2], idx, axis=1), gather(sv[:2], idx, axis=1), cfg.splat_spacing_m,
                              cfg.max_footprint_m, cfg.max_samples_per_axis)
        order = np.argsort(keys, kind="stable")
        keys, idx = gather(keys, order), gather(idx, order)
        full = gather(self._interior_to_full, idx)                   # the same pixels in the h×w image
        # Per pixel and quantity (row, column, height, horizontal, flat): step u, step v, value (fusion.splat),
        # in the grid's cell units so that the samples need no further arithmetic before binning.
        shift, scale = self._grid.cell_frame((0.0, 0.0, 0.0) if position is None else tuple(position.tolist()))
        columns = np.empty((5, 3, idx.size), dtype=np.float32)
        for k in range(3):
            gather(su[k], idx, out=columns[k, 0])
            gather(sv[k], idx, out=columns[k, 1])
            gather(pts[k], full, out=columns[k, 2])
        columns[:3, 2] += shift[:, None]
        columns[:2] *= scale
        columns[3:, :2] = 0.0
        if hvo_h is not None:
            gather(hvo_h.reshape(-1), full, out=columns[3, 2])
        else:
            columns[3, 2] = 1.0
        nz_k = gather(nz.reshape(-1), idx)
        cos2 = np.float32(math.cos(cfg.max_slope_rad) ** 2)
        np.greater_equal(nz_k * nz_k, cos2 * gather(nn.reshape(-1), idx), out=columns[4, 2], casting="unsafe")
        return self._grid.add_cells(splat(columns, keys, cfg.max_samples_per_axis))

    def _make_target(self, pred: Prediction, choice: Choice, pose: tuple[Attitude, Mount],
                     position: Optional[np.ndarray], have_hvo: bool, timings: dict[str, float],
                     evidence: str = "") -> Target:
        cfg = self.config
        point = np.array([choice.north_m, choice.east_m, choice.down_m], dtype=np.float64)
        level = self._confirm.level_m(choice, self._view) if position is not None else math.nan
        if abs(point[2] - level) > cfg.max_level_disagreement_m:   # (False for NaN: no geometry level there)
            # The network proposes the spot; its level is geometry's where the two disagree grossly.
            evidence += f"; level from geometry (the network's depth put it {point[2] - level:+.1f} m down)"
            point[2] = level
        rel = point - position if position is not None else point
        aim = aim_from_offset(rel, pose[0], choice.clearance_m, pose[1])
        clear_used = min(choice.clearance_m, cfg.clearance_saturation_m)
        confidence = (clear_used / cfg.clearance_saturation_m) * choice.flat_share
        confidence *= choice.horizontal_share if have_hvo else cfg.depth_only_confidence
        base, det, age = self._confirm.figures(choice, self._view)
        if aim is None or not all(math.isfinite(v) for v in (aim.angle_x_rad, aim.angle_y_rad, choice.clearance_m,
                                                              confidence)):
            self._kept = None
            return Target.none(pred.frame_id, pred.capture_time_s, "no target: non-finite output", timings)
        self._kept = KeptSpot(choice.north_m, choice.east_m, float(pred.capture_time_s))
        return Target(
            frame_id=pred.frame_id, capture_time_s=pred.capture_time_s, valid=True,
            reason="" if have_hvo else DEGRADED_NO_HVO,
            position_body_frd_m=aim.body_frd_m,
            position_ned_m=point.copy() if position is not None else None,
            range_m=aim.range_m, angle_x_rad=aim.angle_x_rad, angle_y_rad=aim.angle_y_rad,
            size_x_rad=aim.size_x_rad, size_y_rad=aim.size_y_rad, clearance_m=float(choice.clearance_m),
            confidence=float(min(max(confidence, 0.0), 1.0)), timings_s=timings, evidence=evidence,
            geometry_baseline_m=base, geometry_detectable_m=det, geometry_age_s=age)
