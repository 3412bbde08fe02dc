"""Motion-geometry evidence per local NED cell, with a time-based memory (ARCHITECTURE.md §11).

Cells have the fusion grid's size and origin convention (edges at multiples of ``cell_m``), so the two
line up cell for cell. Per cell, from each frame pair (motion.ParallaxResult):
- the smallest obstacle height that frame could have detected there (``detectable``, the worst reliable
  pixel of the cell: every part of the cell must have been measurable);
- whether some pixel stood out: |height| >= half the obstacle height and >= ``detect_sigmas`` σ ("high";
  drops count too: a site must be flat);
- whether the ray of a pixel the flow left unmatched crosses it (fusion.residual: something too thin for the
  flow may stand there). It votes like "high" but neither revokes nor blocks a confirmation on its own.
Across frames: the cell's mean height in each frame is fused by inverse variance (σ = the worst pixel's,
weights decaying with ``memory_s``): sensor noise and rain differ from frame to frame, so pairs that each
detect too little on a noisy flight detect less together (measurements: docs §11). Pairs share keyframes
and DIS's texture errors (it fills a smooth patch, a car's paint, the same way in every pair), so the credit is
capped: the fused detectable height is at least the best single pair's / ``max_fusion_gain`` (1.5: as much as
about two independent pairs; at 2 a parked car's bonnet read as ground was confirmed).
``clear_t`` is the last time a frame measured the cell, found it not high, and the fused evidence was
measurable to the obstacle height and not high. Only a frame that could itself have detected ``renew_factor`` ×
the obstacle height there (1.5 m for 0.5 m: a car) renews it through the fused credit: a hover's pairs cannot see
a car, so a confirmation ends ``memory_s`` after the last pair that could. ``seen_w`` / ``high_w`` are weights
of frames that measured it / found it high. A cell is *geometry-clear* while ``now - clear_t <= memory_s`` and it is not
an obstacle; an *obstacle* when ``high_w >= obstacle_vote_share · seen_w`` (flow has heavy tails: one
odd frame out of many does not make an obstacle; a real one is high in most frames that could see it),
or when its fused height stands out (half the obstacle height and ``detect_sigmas`` fused σ). Each cell also
keeps the NED level of the surface that last confirmed it: heights are judged against each pair's own
local ground (a roof's, on a raised plane: fusion.plane_sweep), so a clear cell within 1 m of a clear cell
at another level (more than the obstacle height plus 3 σ of the difference apart: 1.2 m for 0.5 m) is not
clear (a step between two clear surfaces).
Pure numpy/OpenCV; memory is the grid itself (bounded) and timestamps (bounded in time by construction).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Optional

import cv2
import numpy as np

from edge_landing.runtime.fusion.geometry_memo import ViewMemo, _level_steps, steps_at_cut_sides
from edge_landing.runtime.fusion.grid import recentre
from edge_landing.runtime.fusion.motion import ParallaxResult


class _FrameCells(NamedTuple):
    """One frame's evidence per cell on the bounding box of its cells, whose corner is grid cell (row0, col0)."""

    row0: int
    col0: int
    detectable: np.ndarray
    high: np.ndarray
    suspect: np.ndarray
    mean_h: np.ndarray
    mean_down: np.ndarray
    unmatched: np.ndarray       # a ray the flow left unmatched crosses it (fusion.residual)
    thin: np.ndarray            # the largest thin-obstacle factor of its pixels (MotionConfig.thin_obstacle_m)


@dataclass(frozen=True)
class GeometryView:
    """Geometry evidence on a window of cells (rows north, columns east), as of ``time_s``.

    ``clear``: confirmed clear of obstacles of ``obstacle_height_m``, and at the level of the clear cells around
    it (no step between two clear surfaces: ``_level_steps``); ``obstacle``: something at least that
    tall was seen; ``detectable_m``: the smallest height detectable there with the evidence fused within the
    memory (inf: never measured); ``baseline_m``: the baseline of the frame that last confirmed the cell (NaN: never);
    ``clear_age_s``: time since that confirmation (inf: never); ``clear_down_m``: the NED down of the surface that
    last confirmed it, measured against that pair's ground plane (NaN: never).
    """

    time_s: float
    obstacle_height_m: float
    clear: np.ndarray
    obstacle: np.ndarray
    detectable_m: np.ndarray
    baseline_m: np.ndarray
    clear_age_s: np.ndarray
    clear_down_m: np.ndarray


class GeometryGrid:
    """Square grid of cells following the vehicle (whole-cell moves), holding motion-geometry evidence."""

    def __init__(self, cell_m: float, radius_m: float, memory_s: float, obstacle_height_m: float,
                 detect_sigmas: float = 3.0, obstacle_vote_share: float = 0.3, max_unexplained_share: float = 0.1,
                 grow_m: float = 1.0, min_high_share: float = 0.25, max_fusion_gain: float = 1.5,
                 renew_factor: float = 3.0):
        self.cell_m = float(cell_m)
        self.size = max(3, int(math.ceil(2.0 * radius_m / cell_m)))
        self.memory_s = float(memory_s)
        self.obstacle_height_m = float(obstacle_height_m)
        self.detect_sigmas = float(detect_sigmas)
        self.obstacle_vote_share = float(obstacle_vote_share)
        self.max_unexplained_share = float(max_unexplained_share)
        self.grow_m = float(grow_m)
        self.min_high_share = float(min_high_share)
        self.max_fusion_gain = max(1.0, float(max_fusion_gain))
        self.renew_factor = max(self.max_fusion_gain, float(renew_factor))
        # A pixel covers up to a few cells on the ground at range, and flow smears an obstacle's edge into the
        # ground around it (its top is placed at a height read low): obstacles are grown by ``grow_m`` after
        # the vote (growing each frame's outliers before it made most open ground an "obstacle").
        k = 2 * max(1, int(math.ceil(self.grow_m / self.cell_m))) + 1
        self._grow = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
        r = 2 * max(1, int(math.ceil(1.0 / self.cell_m))) + 1       # cells within 1 m: levels must agree
        self._reach = np.ones((r, r), np.uint8)
        # A confirmed cell's level is known to σ <= obstacle height / detect_sigmas: two such levels differ by
        # more than the obstacle height plus detect_sigmas of their difference's σ only at a real step (with
        # the obstacle height alone, flow noise between neighbouring confirmed cells moved spots).
        self._level_step_m = self.obstacle_height_m * (1.0 + math.sqrt(2.0))
        self.north0_m = -self.size * self.cell_m / 2.0
        self.east0_m = -self.size * self.cell_m / 2.0
        self._time_s: Optional[float] = None
        self.clear()

    def clear(self) -> None:
        s = self.size
        self._det = np.full((s, s), np.inf, np.float32)          # best detectable height within memory
        self._det_t = np.full((s, s), -np.inf)                   # when it was measured
        self._clear_t = np.full((s, s), -np.inf)                 # last frame that confirmed the cell
        self._clear_base = np.full((s, s), np.nan, np.float32)   # that frame's baseline
        self._clear_down = np.full((s, s), np.nan, np.float32)   # NED down of the surface that frame measured
        self._w = np.zeros((2, s, s), np.float32)                # decayed weights: seen, high
        self._fused = np.zeros((2, s, s), np.float32)            # decayed Σ 1/σ², Σ h/σ² of the cell's heights
        self._time_s = None
        self._box: Optional[tuple[int, int, int, int]] = None    # rows r0:r1, cols c0:c1 that ever held evidence
        # Grid cell (r, c) is array cell (r + dr, c + dc): moves are applied to the arrays only when evidence is
        # added (the vehicle moves a cell most frames, the stage runs on few of them).
        self._pending = (0, 0)
        self._memo = ViewMemo()

    def centre_on(self, north_m: float, east_m: float) -> None:
        """Move so that (north, east) is near the centre (same rule as fusion's TopDownGrid), keeping the overlap.

        Only the box and the pending move change here. Every cell that is still in the box stayed inside the
        grid through all the moves since the arrays were last moved (each move clips the box to the grid), so
        it reads its own value at the summed offset; every cell outside the box holds the fill.
        """
        (self.north0_m, self.east0_m), (dr, dc) = recentre(self.north0_m, self.east0_m, north_m, east_m, self.size,
                                                           self.cell_m)
        # Without evidence every array holds its "never measured" fill: nothing to move.
        if (dr or dc) and self._box is not None:
            # Cell (r, c) moved to (r - dr, c - dc).
            b = (max(self._box[0] - dr, 0), min(self._box[1] - dr, self.size),
                 max(self._box[2] - dc, 0), min(self._box[3] - dc, self.size))
            self._box = b if b[0] < b[1] and b[2] < b[3] else None
            self._pending = (self._pending[0] + dr, self._pending[1] + dc)

    def _apply_move(self) -> None:
        """Write the pending move into the arrays: the box's cells to their place, the fill everywhere else."""
        dr, dc = self._pending
        if dr == 0 and dc == 0:
            return
        self._pending = (0, 0)
        self._memo = ViewMemo()
        box = self._box
        for name, fill in (("_det", np.inf), ("_det_t", -np.inf), ("_clear_t", -np.inf), ("_clear_base", np.nan),
                           ("_clear_down", np.nan), ("_w", 0.0), ("_fused", 0.0)):
            old = getattr(self, name)
            new = np.full_like(old, fill)
            if box is not None:
                r0, r1, c0, c1 = box
                new[..., r0:r1, c0:c1] = old[..., r0 + dr:r1 + dr, c0 + dc:c1 + dc]
            setattr(self, name, new)

    def add(self, result: ParallaxResult) -> int:
        """Merge one frame's evidence; returns the number of cells it measured."""
        self._apply_move()
        self._memo = ViewMemo()
        t = result.time_s
        if self._time_s is not None:
            if t < self._time_s:            # time went backwards: nothing older can be trusted
                self.clear()
            else:
                decay = np.float32(math.exp(-(t - self._time_s) / self.memory_s))
                self._w *= decay
                self._fused *= decay
        self._time_s = t
        frame = self._frame_cells(result)
        if frame is None:
            return 0
        r0, c0, det, high, suspect, mean_h, mean_down, unmatched, thin = frame
        win = (slice(r0, r0 + det.shape[0]), slice(c0, c0 + det.shape[1]))
        r1, c1 = r0 + det.shape[0], c0 + det.shape[1]
        box = self._box
        self._box = (r0, r1, c0, c1) if box is None else (min(box[0], r0), max(box[1], r1), min(box[2], c0),
                                                          max(box[3], c1))
        measured = np.isfinite(det)
        best = self._det[win]
        expired = (t - self._det_t[win]) > self.memory_s
        better = measured & ((det <= best) | expired)
        best[better] = det[better]
        self._det_t[win][better] = t
        usable = measured & (det > 0) & np.isfinite(mean_h)
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.where(usable, (self.detect_sigmas / det) ** 2, 0.0).astype(np.float32)
        self._fused[0][win] += w
        self._fused[1][win] += w * np.where(usable, mean_h, 0.0).astype(np.float32)
        fused_det, fused_high = self._fused_evidence(self._fused[:, win[0], win[1]], best)
        # The fused credit only where no frame within the memory found the cell high: a thin wall or pole that
        # DIS smooths to a fraction of its height stands out in few frames (too few for the vote) and must not
        # be confirmed by averaging the frames that missed it. And only from a frame that could itself have seen
        # a car there (``renew_factor`` × the obstacle height): a hover's or a descent's pairs, detecting metres,
        # must not renew what the pairs able to see one confirmed seconds before. Not the credit's own cap
        # (1.5×): in heavy rain every moving pair detects 0.7-1.5 m, and confirmation rests on renewing by them.
        informative = det <= self.renew_factor * self.obstacle_height_m
        # A thin wall reads at a fraction of its height where the flow's patch is wider than it (``thin``: how
        # many times): this frame confirms only what it could have seen of one (MotionConfig.thin_obstacle_m).
        credit = (fused_det * thin <= self.obstacle_height_m) & (self._w[1][win] < 0.5) & informative
        confirm = measured & ((det * thin <= self.obstacle_height_m) | credit) & ~fused_high & ~high & ~suspect
        self._clear_t[win][confirm] = t
        self._clear_t[win][(high | suspect) & ~confirm] = -np.inf
        self._clear_base[win][confirm] = np.float32(result.baseline_m)
        self._clear_down[win][confirm] = mean_down[confirm]
        # Unmatched pixels vote with the high ones but neither revoke nor block a confirmation by themselves: open
        # ground has a few in some pairs, a person in most (fusion.residual).
        self._w[0][win] += measured | high | unmatched
        self._w[1][win] += high | unmatched
        return int(measured.sum())

    def _fused_evidence(self, fused: np.ndarray, best_det: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(detectable height, stands out) of the inverse-variance fused heights (2×H×W sums), the credit for
        fusing capped at ``max_fusion_gain`` below the best single pair's detectable height ``best_det``."""
        with np.errstate(divide="ignore", invalid="ignore"):
            det = np.where(fused[0] > 0, self.detect_sigmas / np.sqrt(fused[0]), np.inf)
            det = np.maximum(det, best_det / self.max_fusion_gain).astype(np.float32)
            dev = np.abs(np.where(fused[0] > 0, fused[1] / fused[0], 0.0))
            high = np.isfinite(det) & (dev >= 0.5 * self.obstacle_height_m) & (dev >= det)
        return det, high

    def _cell_index(self, north_m: np.ndarray, east_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows, columns, inside the grid) of the cells holding points north, east (local NED)."""
        scale = 1.0 / self.cell_m
        r = np.floor((north_m - self.north0_m) * scale).astype(np.int64)
        c = np.floor((east_m - self.east0_m) * scale).astype(np.int64)
        return r, c, (r >= 0) & (r < self.size) & (c >= 0) & (c < self.size)

    def _cells_of(self, ne_m: Optional[np.ndarray]) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """(rows, columns) of the grid cells holding north, east points (N×2; None: none inside the grid)."""
        if ne_m is None or len(ne_m) == 0:
            return None
        r, c, inside = self._cell_index(ne_m[:, 0], ne_m[:, 1])
        return (r[inside], c[inside]) if inside.any() else None

    def _frame_cells(self, result: ParallaxResult) -> Optional[_FrameCells]:
        """This frame's evidence per cell on the bounding box of its cells (None: no cell inside the grid)."""
        ned = result.ned_m
        ok = np.isfinite(ned[0])
        if not ok.any():
            return None
        r, c, inside = self._cell_index(ned[0][ok], ned[1][ok])
        if not inside.any():
            return None
        r, c = r[inside], c[inside]
        hgt = result.height_m[ok][inside]
        down = ned[2][ok][inside]
        det = result.detectable_m[ok][inside]
        sigma = result.sigma_m[ok][inside]
        odd = self._cells_of(result.unmatched_ne_m)
        ar, ac = (r, c) if odd is None else (np.concatenate([r, odd[0]]), np.concatenate([c, odd[1]]))
        r0, r1, c0, c1 = max(int(ar.min()) - 1, 0), min(int(ar.max()) + 2, self.size), \
            max(int(ac.min()) - 1, 0), min(int(ac.max()) + 2, self.size)
        rows, cols = r1 - r0, c1 - c0
        idx = (r - r0) * cols + (c - c0)
        n = rows * cols
        # Measured: a height (finite); confirmable only where also resolved (finite detectable height: the
        # patch's footprint is small enough). Unexplained: the model failed where the reference did see it.
        measured_px = np.isfinite(hgt)
        unexplained_px = ~np.isfinite(det) if result.unexplained is None else result.unexplained[ok][inside]
        n_rel = np.bincount(idx[measured_px], minlength=n)
        n_unrel = np.bincount(idx[unexplained_px & ~measured_px], minlength=n)
        worst = np.full(n, -np.inf, np.float32)
        np.maximum.at(worst, idx[measured_px], det[measured_px])   # inf when a pixel of the cell is unresolved
        thin = np.ones(n, np.float32)
        if result.thin_factor is not None:
            np.maximum.at(thin, idx[measured_px], result.thin_factor[ok][inside][measured_px])
        with np.errstate(invalid="ignore"):
            # Both signs: a landing site must be flat, and a drop (a gap between packed cars seen as the
            # "ground" at their roofs, a roof's edge, a ditch) is as disqualifying as something standing up.
            # Unresolved pixels report obstacles too (a smoothed obstacle still reads high, only lower).
            dev = np.abs(hgt)
            high_px = measured_px & (dev >= 0.5 * self.obstacle_height_m) & (dev >= self.detect_sigmas * sigma)
        # Flow errors are heavy-tailed (a few % of pixels on open ground pass 3σ): a cell stands out in this
        # frame when a quarter of its pixels do (any one, for cells of up to four pixels, at long range).
        n_high = np.bincount(idx[high_px], minlength=n)
        high = ((n_high > 0) & (n_high >= self.min_high_share * n_rel)).reshape(rows, cols)
        unmatched = np.zeros((rows, cols), bool)
        if odd is not None:   # something too thin for the flow may stand there (fusion.residual)
            unmatched = (np.bincount((odd[0] - r0) * cols + (odd[1] - c0), minlength=n) > 0).reshape(rows, cols)
        # Every part of a cell must be explained by the plane model: pixels the flow could not match (occlusion
        # by something tall, a parallax too large for the pair) are not "no evidence" but unexplained, so a
        # cell with more than a few of them is not measured in this frame, and one with mostly unexplained
        # pixels is suspect (its earlier confirmation is revoked: a car's top often fails the photometric check).
        total = n_rel + n_unrel
        measured = (n_rel > 0) & (n_unrel <= self.max_unexplained_share * total)
        suspect = (n_unrel > 0.5 * total).reshape(rows, cols)
        det_c = np.where(measured, worst, np.inf).astype(np.float32).reshape(rows, cols)
        det_c = _fill_holes(det_c, (np.bincount(idx, minlength=n) == 0).reshape(rows, cols))  # no pixel at all
        suspect = cv2.dilate(suspect.view(np.uint8), self._grow).astype(bool)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_h = (np.bincount(idx[measured_px], weights=hgt[measured_px], minlength=n) / n_rel).reshape(rows, cols)
            mean_down = (np.bincount(idx[measured_px], weights=down[measured_px], minlength=n) / n_rel
                         ).reshape(rows, cols).astype(np.float32)
        return _FrameCells(r0, c0, det_c, high, suspect, mean_h, mean_down, unmatched, thin.reshape(rows, cols))

    def view(self, north0_m: float, east0_m: float, shape: tuple[int, int], now_s: float) -> GeometryView:
        """The evidence on a window of cells whose corner is (north0, east0) (cells outside: no evidence).

        Only the cells inside the box that has ever held evidence (``_box``) are computed; every other cell
        of the window reads "never measured" (not clear, no obstacle, nothing detectable, no baseline).
        """
        rows, cols = shape
        dr = int(round((north0_m - self.north0_m) / self.cell_m))
        dc = int(round((east0_m - self.east0_m) / self.cell_m))
        det = np.full((rows, cols), np.inf, np.float32)
        high = np.zeros((rows, cols), dtype=bool)
        age = np.full((rows, cols), np.inf)
        base = np.full((rows, cols), np.nan, np.float32)
        clear = np.zeros((rows, cols), dtype=bool)
        down = np.full((rows, cols), np.nan, np.float32)
        box = self._box
        v = None
        if box is not None:
            # Grid cell (r, c) is window cell (r - dr, c - dc): the evidence box clipped to both.
            r0, r1 = max(box[0], dr), min(box[1], dr + rows)
            c0, c1 = max(box[2], dc), min(box[3], dc + cols)
            if r0 < r1 and c0 < c1:
                pr, pc = self._pending
                g = (slice(r0 + pr, r1 + pr), slice(c0 + pc, c1 + pc))          # in the arrays
                v = (slice(r0 - dr, r1 - dr), slice(c0 - dc, c1 - dc))
                decay = 1.0 if self._time_s is None else math.exp(-max(now_s - self._time_s, 0.0) / self.memory_s)
                seen = self._w[0][g] * decay
                high_w = self._w[1][g] * decay
                det[v], fused_high = self._fused_now(g, now_s)
                high[v] = ((high_w > 0) & (high_w >= self.obstacle_vote_share * seen)) | fused_high
                since = age[v]
                np.subtract(now_s, self._clear_t[g], out=since)
                if not math.isfinite(now_s):       # (with a finite time, never-confirmed cells come out +inf already)
                    since[~np.isfinite(since)] = np.inf
                base[v] = self._clear_base[g]
                down[v] = self._clear_down[g]
        obstacle = cv2.dilate(high.view(np.uint8), self._grow).astype(bool)
        if v is not None:       # only cells inside the evidence box can be clear (age is inf outside)
            clear[v] = (age[v] <= self.memory_s) & ~obstacle[v]
            clear[v] &= ~self._steps_now(g, clear[v])
        return GeometryView(now_s, self.obstacle_height_m, clear, obstacle, det, base, age, down)

    def _fused_now(self, g: tuple[slice, slice], now_s: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_fused_evidence` on array cells ``g`` with the single-pair heights still within the memory at
        ``now_s``. Between stage runs only that "within" mask changes with time, and only by cells leaving it
        (now - t grows with now and shrinks with t, rounding included): while time has not gone back and the
        oldest height within at the last computation still is, the mask is the same and so is the result
        (elementwise, so a window of it serves a smaller ``g``). The memo is dropped whenever the arrays change."""
        memo = self._memo
        sub = memo.inside(g)
        if sub is not None and memo.fused is not None:
            then_s, oldest_s, det, fused_high = memo.fused
            if now_s >= then_s and now_s - oldest_s <= self.memory_s:
                return det[sub], fused_high[sub]
        det_t = self._det_t[g]
        within = now_s - det_t <= self.memory_s
        best = np.where(within, self._det[g], np.inf).astype(np.float32)
        det, fused_high = self._fused_evidence(self._fused[:, g[0], g[1]], best)
        oldest_s = float(det_t[within].min()) if within.any() else math.inf     # none within: none will be
        memo.box, memo.fused = g, (now_s, oldest_s, det, fused_high)
        return det, fused_high

    def _steps_now(self, g: tuple[slice, slice], clear: np.ndarray) -> np.ndarray:
        """:func:`_level_steps` of the levels of the ``clear`` cells among array cells ``g``.

        Reused from the last call when the arrays did not change since, ``g`` lies within its cells and the clear
        cells there are the same (a cell without a clear level counts exactly as a cell beyond the border:
        neither takes part in the dilation or the erosion); where clear cells fell outside ``g`` (the grid moved),
        only the cells within the kernel's reach of those sides are recomputed."""
        memo = self._memo
        sub = memo.inside(g, steps=True)
        if sub is not None and memo.steps is not None:
            was_clear, steps = memo.steps
            if np.array_equal(was_clear[sub], clear):
                (r, c), step = sub, self._level_step_m
                cut = (bool(was_clear[:r.start].any()), bool(was_clear[r.stop:].any()),
                       bool(was_clear[:, :c.start].any()), bool(was_clear[:, c.stop:].any()))
                if not any(cut):
                    return steps[sub]
                steps = steps_at_cut_sides(steps[sub], clear, self._clear_down[g], cut, step, self._reach)
                memo.steps_box, memo.steps = g, (clear.copy(), steps)
                return steps
        steps = _level_steps(np.where(clear, self._clear_down[g], np.nan), self._level_step_m, self._reach)
        memo.steps_box, memo.steps = g, (clear.copy(), steps)
        return steps


def _fill_holes(det: np.ndarray, empty: np.ndarray, min_neighbours: int = 5) -> np.ndarray:
    """A cell no pixel fell in, amid measured ones, takes the worst of its neighbours (pixels sample the
    ground about a cell apart at range, leaving single-cell holes that are not evidence of anything). Cells
    with pixels that were not measured stay unmeasured."""
    measured = np.isfinite(det)
    count = cv2.boxFilter(measured.view(np.uint8), -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    worst = cv2.dilate(np.where(measured, det, np.float32(0.0)), np.ones((3, 3), np.uint8),
                       borderType=cv2.BORDER_CONSTANT, borderValue=0.0)
    fill = empty & ~measured & (count >= min_neighbours)
    return np.where(fill, worst, det).astype(np.float32)
