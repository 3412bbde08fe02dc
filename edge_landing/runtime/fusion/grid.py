"""The top-down ground grid of fusion (ARCHITECTURE.md §6 steps 4-5), pure numpy + OpenCV.

Per cell it keeps, as PX4-Avoidance's safe_landing_planner does, the (decayed) number of samples, the sum
and the sum of squares of the height (so mean and spread), the sum of horizontal votes from the net and
the sum of flat-by-depth votes. A cell is landable when it has enough support, a small height spread and
large enough horizontal and flat shares, judged within one frame; across frames (NED mode) only these
verdicts are accumulated, never raw heights (see :class:`TopDownGrid`). Clearance is the metric distance
to the nearest cell that is not landable.

Samples come from fusion.splat: each pixel spread over its ground footprint.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import cv2
import numpy as np

from edge_landing.runtime.fusion.cells import clearance_from_mask, fill_sampling_holes
from edge_landing.runtime.fusion.grid_view import GridView

__all__ = ["CellRules", "GridView", "TopDownGrid", "clearance_from_mask", "fill_sampling_holes",
           "judge_cells", "recentre"]

# Sum arrays kept per cell, in this order: weight (count), height, height², horizontal votes, flat votes.
_N_SUMS = 5
_SEEN = _N_SUMS + 2  # layer index of the "last seen" weight (after the two vote weights)


@dataclass(frozen=True)
class CellRules:
    """When a cell is landable (see FusionConfig for the meaning of each field)."""

    min_points_per_cell: float
    max_height_spread_m: float
    min_horizontal_share: float
    min_flat_share: float
    use_hvo: bool = True
    min_neighbours_to_fill: int = 6
    min_vote_share: float = 0.6
    # Memory bounded in time (NED): a cell counts as observed while its "last seen" weight, set to 1 by every
    # frame that observes it and decayed with the evidence (exp(-dt/decay_s)), is at least this; i.e. for
    # decay_s·ln(1/min_seen_weight) seconds after it was last seen, whatever the frame rate.
    min_seen_weight: float = math.exp(-1.5)


def recentre(north0_m: float, east0_m: float, north_m: float, east_m: float, size: int,
             cell_m: float) -> tuple[tuple[float, float], tuple[int, int]]:
    """The NED origin (north, east) of a ``size``-cell square grid that puts (north, east) near its centre, on
    whole cells, and the shift (rows, columns) of the cells from the origin (north0, east0) to it."""
    half = size * cell_m / 2.0
    n0 = math.floor((north_m - half) / cell_m) * cell_m
    e0 = math.floor((east_m - half) / cell_m) * cell_m
    return (n0, e0), (int(round((n0 - north0_m) / cell_m)), int(round((e0 - east0_m) / cell_m)))


class TopDownGrid:
    """Square grid of ``size`` × ``size`` cells of ``cell_m`` metres whose origin can move with the vehicle.

    Each frame's samples are binned into a small per-frame crop (the bounding box of what the camera saw,
    plus a one-cell ring) and judged there: support, height spread, horizontal and flat shares, all from
    this frame alone. In vehicle mode that verdict is the grid. In NED mode (:meth:`evaluate` with
    ``frame="ned"``) the per-frame sums and verdicts are added to decayed totals: per cell the observation
    weight (frames that saw it) and the landable weight (frames that judged it landable). Heights are never
    compared across frames: the network's depth scale wanders by ~1 % from frame to frame (0.5-1 m at
    60-80 m), far more than the 0.1 m spread limit, while within one frame it is consistent. A cell is
    landable in NED when its decayed landable weight is at least ``min_vote_share`` of its observation
    weight: one flickering verdict does not unmake a spot, and a cell seen clear for long, once seen blocked
    in every frame, drops below the share after decay_s·ln(1/min_vote_share) (1 s with 2 s and 0.6).

    Clearing, decaying and moving replace the arrays with new ones instead of writing into them, so a
    :class:`GridView` handed out earlier never changes under its reader.
    """

    def __init__(self, cell_m: float, radius_m: float):
        self.cell_m = float(cell_m)
        self.size = max(3, int(math.ceil(2.0 * radius_m / cell_m)))
        self.north0_m = -self.size * self.cell_m / 2.0
        self.east0_m = -self.size * self.cell_m / 2.0
        self._buf = np.empty((_N_SUMS, 0), dtype=np.float64)    # per-frame binning buffer (never handed out)
        self.clear()

    # One float32 array holds the five sums, the two vote weights and the "last seen" weight, so that
    # decaying and moving the grid
    # is one pass over memory (float32 is plenty: per-frame judging is done in float64 on the crop).
    @property
    def sums(self) -> np.ndarray:
        return self._acc[:_N_SUMS]

    @property
    def votes(self) -> np.ndarray:
        return self._acc[_N_SUMS:_SEEN]

    @property
    def seen(self) -> np.ndarray:
        seen: np.ndarray = self._acc[_SEEN]
        return seen

    def clear(self, ref_down_m: float = 0.0) -> None:
        """Forget everything. Heights are stored relative to ``ref_down_m`` (keeps Σh² well conditioned)."""
        self.ref_down_m = float(ref_down_m)
        s = self.size
        self._acc = np.zeros((_SEEN + 1, s, s), dtype=np.float32)   # calloc: untouched pages cost nothing
        self._factor = 1.0                                       # decay not yet applied to _acc
        self._frame: Optional[tuple[int, int, np.ndarray]] = None   # (row0, col0, sums crop) of the last add
        self._fresh = True                                       # no GridView holds _acc yet

    def decay(self, factor: float) -> None:
        """Scale all evidence by ``factor`` (applied lazily, together with the next move)."""
        self._factor *= min(max(factor, 0.0), 1.0)

    def centre_on(self, north_m: float, east_m: float) -> None:
        """Move the grid so that (north, east) is near its centre, keeping what overlaps (whole cells only).

        Also applies any pending decay; moving and decaying write one new array (never the old one).
        """
        (self.north0_m, self.east0_m), (dr, dc) = recentre(self.north0_m, self.east0_m, north_m, east_m, self.size,
                                                           self.cell_m)
        if dr != 0 or dc != 0 or self._factor != 1.0:
            self._rebuild(dr, dc)

    def _rebuild(self, dr: int, dc: int) -> None:
        """new[:, r, c] = old[:, r + dr, c + dc] · pending decay (zeros where that falls outside)."""
        s, a = self.size, self._acc
        if dr == 0 and dc == 0:                           # decay only: one pass, no zeroing
            self._acc, self._factor, self._fresh = a * np.float32(self._factor), 1.0, True
            return
        if abs(dr) >= s or abs(dc) >= s:
            self._acc, self._factor, self._fresh = np.zeros_like(a), 1.0, True
            return
        # Write every cell once: the overlap scaled, the uncovered strips zeroed (not zeros + copy: two passes).
        new = np.empty_like(a)
        r0, r1, c0, c1 = max(0, -dr), s - max(0, dr), max(0, -dc), s - max(0, dc)
        np.multiply(a[:, r0 + dr:r1 + dr, c0 + dc:c1 + dc], np.float32(self._factor), out=new[:, r0:r1, c0:c1])
        new[:, :r0] = 0.0
        new[:, r1:] = 0.0
        new[:, r0:r1, :c0] = 0.0
        new[:, r0:r1, c1:] = 0.0
        self._acc, self._factor, self._fresh = new, 1.0, True

    def cell_frame(self, offset_ned_m: Sequence[float] = (0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.float32]:
        """(shift, scale) that take a point relative to ``offset_ned_m`` into this grid's cell units.

        row = (north + shift[0]) · scale, column = (east + shift[1]) · scale (floats: the cell is their floor),
        height = down + shift[2] (metres from ``ref_down_m``). float32, like the per-sample arithmetic.
        """
        shift = np.array([offset_ned_m[0] - self.north0_m, offset_ned_m[1] - self.east0_m,
                          offset_ned_m[2] - self.ref_down_m], dtype=np.float32)
        return shift, np.float32(1.0 / self.cell_m)

    def add_cells(self, samples: np.ndarray) -> int:
        """Bin one frame's samples for :meth:`evaluate`: rows (row, column, height, horizontal, flat) × N.

        Row and column are in cell units (:meth:`cell_frame`), height in metres from ``ref_down_m``, the votes
        in [0, 1]. Rows 0-1 are overwritten. Returns how many fell inside the grid. Binning covers only the
        bounding box of the samples (plus a one-cell ring for hole filling), not the whole grid; samples
        outside the grid go to one extra bin that is dropped, which is cheaper than masking five arrays.
        """
        s = self.size
        self._frame = None
        if samples.shape[1] == 0:
            return 0
        rc = samples[:2]
        np.floor(rc, out=rc)
        r_lo, r_hi = _min_max(rc[0])
        c_lo, c_hi = _min_max(rc[1])
        r0, r1 = max(r_lo - 1, 0), min(r_hi + 2, s)
        c0, c1 = max(c_lo - 1, 0), min(c_hi + 2, s)
        if r0 >= r1 or c0 >= c1:
            return 0
        rows, cols = r1 - r0, c1 - c0
        n_cells = rows * cols
        # Samples off the grid go to the extra bin n_cells. Only an axis that reaches past the grid needs the test.
        outside = None
        if r_lo < 0 or r_hi >= s:
            outside = (rc[0] < r0) | (rc[0] >= r1)
        if c_lo < 0 or c_hi >= s:
            off_cols = (rc[1] < c0) | (rc[1] >= c1)
            outside = off_cols if outside is None else outside | off_cols
        # The crop's flat index, in float32 (whole numbers below 2^24: exact), then one conversion.
        flat_f = rc[0]
        flat_f *= np.float32(cols)
        flat_f += rc[1]
        flat_f -= np.float32(r0 * cols + c0)
        if outside is not None:
            flat_f[outside] = n_cells
        idx = flat_f.astype(np.intp)                        # intp: np.bincount would convert anything else first
        h = samples[2].astype(np.float64)
        if self._buf.shape[1] < n_cells + 1:                 # reused across frames: no fresh pages to fault in
            self._buf = np.empty((_N_SUMS, n_cells + 1), dtype=np.float64)
        crop = self._buf[:, :n_cells + 1]
        crop[0] = np.bincount(idx, minlength=n_cells + 1)
        crop[1] = np.bincount(idx, weights=h, minlength=n_cells + 1)
        np.multiply(h, h, out=h)
        crop[2] = np.bincount(idx, weights=h, minlength=n_cells + 1)
        crop[3] = np.bincount(idx, weights=samples[3], minlength=n_cells + 1)
        crop[4] = np.bincount(idx, weights=samples[4], minlength=n_cells + 1)
        inside = int(idx.shape[0] - crop[0, n_cells])
        self._frame = (r0, c0, crop[:, :n_cells].reshape(_N_SUMS, rows, cols))
        return inside

    def evaluate(self, rules: CellRules, frame: str) -> GridView:
        """Judge the frame added last and return the landable mask and the clearance map (metres), as a snapshot.

        ``frame="vehicle"``: the grid is this frame alone. ``frame="ned"``: this frame's sums and verdicts are
        added to the decayed totals (see the class docstring). Work is limited to the bounding box of observed
        cells plus a one-cell ring: everything outside is unobserved, so not landable, and the ring makes the
        crop's distance transform exact (the nearest outside cell is never nearer than the ring cell between).
        """
        s = self.size
        landable = np.zeros((s, s), dtype=bool)
        clearance = np.zeros((s, s), dtype=np.float32)
        if self._factor != 1.0:
            self._rebuild(0, 0)
        if self._frame is not None:
            r0, c0, crop = self._frame
            self._frame = None
            crop = fill_sampling_holes(crop, rules.min_points_per_cell, rules.min_neighbours_to_fill, in_place=True)
            ok = judge_cells(crop, rules)
            win = (slice(r0, r0 + crop.shape[1]), slice(c0, c0 + crop.shape[2]))
            if frame == "ned":
                if not self._fresh:                           # a view holds _acc: do not write into it
                    self._acc = self._acc.copy()
                acc = self._acc[(slice(None),) + win]
                acc[:_N_SUMS] += crop
                seen_now = crop[0] >= rules.min_points_per_cell
                acc[_N_SUMS] += seen_now
                acc[_N_SUMS + 1] += ok
                acc[_SEEN][seen_now] = 1.0
            else:
                self._acc = np.zeros(self._acc.shape, dtype=np.float32)
                acc = self._acc[(slice(None),) + win]
                acc[:_N_SUMS] = crop
                acc[_N_SUMS] = crop[0] >= rules.min_points_per_cell
                acc[_N_SUMS + 1] = ok
                acc[_SEEN] = acc[_N_SUMS]
        self._fresh = False                                   # handed out below: copy before writing into them
        # Observed = seen recently (time-bounded), not "has decayed samples": a decayed count outlives the last
        # observation by longer the higher the frame rate (9-13 s at 30 fps with decay_s 2 and threshold 1).
        observed = (self.seen >= rules.min_seen_weight) & (self.sums[0] > 0)
        rows = np.flatnonzero(observed.any(axis=1))
        cols = np.flatnonzero(observed.any(axis=0))
        if rows.size:
            r0, r1 = max(int(rows[0]) - 1, 0), min(int(rows[-1]) + 2, s)
            c0, c1 = max(int(cols[0]) - 1, 0), min(int(cols[-1]) + 2, s)
            obs_w, land_w = self.votes[:, r0:r1, c0:c1]
            landable[r0:r1, c0:c1] = observed[r0:r1, c0:c1] & (obs_w > 0) & (land_w >= rules.min_vote_share * obs_w)
            # The grid edge counts as unknown: nothing beyond it was looked at.
            landable[0, :] = landable[-1, :] = False
            landable[:, 0] = landable[:, -1] = False
            clearance[r0:r1, c0:c1] = clearance_from_mask(landable[r0:r1, c0:c1], self.cell_m)
        return GridView(frame, self.cell_m, self.north0_m, self.east0_m, self.ref_down_m, self.sums, landable,
                        clearance, self.votes, self.seen, rules.min_seen_weight)


def _min_max(x: np.ndarray) -> tuple[int, int]:
    """(min, max) of a float32 row of whole numbers, in one pass."""
    lo, hi, _, _ = cv2.minMaxLoc(x)
    return int(lo), int(hi)


def judge_cells(sums: np.ndarray, rules: CellRules) -> np.ndarray:
    """Landable verdict of each cell of one frame's sums (5 × rows × cols), without divisions.

    share >= x  <=>  Σvotes >= x·count, and spread <= σ  <=>  count·Σh² - (Σh)² <= (σ·count)².
    """
    count, s_h, s_h2, s_hor, s_flat = sums
    ok: np.ndarray = (count >= rules.min_points_per_cell) & (s_flat >= rules.min_flat_share * count)
    if rules.use_hvo:
        ok &= s_hor >= rules.min_horizontal_share * count
    sigma_n = rules.max_height_spread_m * count
    ok &= count * s_h2 - s_h * s_h <= sigma_n * sigma_n
    return ok
