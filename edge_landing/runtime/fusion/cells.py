"""Per-cell helpers of fusion's grid (ARCHITECTURE.md §6 step 5): sampling-hole filling and clearance.

Pure numpy + OpenCV, no state. Cells: rows north, columns east, ``cell_m`` metres square.
"""
from __future__ import annotations

import math
from typing import Optional

import cv2
import numpy as np


def gather(a: np.ndarray, indices: np.ndarray, axis: Optional[int] = None, out: Optional[np.ndarray] = None
           ) -> np.ndarray:
    """np.take for indices in range by construction. mode="wrap" because numpy's default ("raise") checks each
    index and, with ``out``, gathers into a buffer first: about twice the time per gather (numpy 2.4,
    docs/MEASUREMENTS.md)."""
    return np.take(a, indices, axis=axis, out=out, mode="wrap")


def fill_sampling_holes(sums: np.ndarray, min_count: float, min_neighbours: int, in_place: bool = False
                        ) -> np.ndarray:
    """Give an empty cell amid observed ones the pooled sums of its 3×3 neighbourhood.

    Footprint samples are spaced about one cell apart, so a cell inside observed ground can miss every
    sample; left empty it would count as an obstacle. It gets the neighbours' pooled samples instead,
    whose height spread then includes the differences between neighbours (a step stays a step).
    Returns ``sums`` itself when nothing is filled, else a filled copy (or ``sums``, filled, with
    ``in_place``). ``min_neighbours`` > 8 disables it.
    """
    if min_neighbours > 8:
        return sums
    observed = (sums[0] >= min_count).view(np.uint8)
    rows, cols = observed.shape
    # 3×3 sum with zeros outside; for an unobserved cell it is the number of observed neighbours.
    neighbours = cv2.boxFilter(observed, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    candidate = (observed == 0) & (neighbours >= min_neighbours)
    candidate[0, :] = candidate[-1, :] = False            # border cells lack a full neighbourhood
    candidate[:, 0] = candidate[:, -1] = False
    holes = np.flatnonzero(candidate)
    if holes.size == 0:
        return sums
    flat = sums.reshape(sums.shape[0], -1)                 # a view unless the layout needs a copy
    # All 8 neighbours of every hole in one gather per sum (1-D np.take: several times faster than fancy
    # indexing), then added in the neighbour order below (from 0, and 0 + x is x: binned sums hold no -0.0).
    offsets = np.array([-cols - 1, -cols, -cols + 1, -1, 1, cols - 1, cols, cols + 1])
    near = (holes[None, :] + offsets[:, None]).ravel()
    gathered = np.empty((sums.shape[0], near.size), dtype=flat.dtype)
    for k in range(sums.shape[0]):
        gather(flat[k], near, out=gathered[k])               # in range: no hole is on the border
    gathered = gathered.reshape(sums.shape[0], 8, holes.size)
    pooled = gathered[:, 0].copy()
    for j in range(1, 8):
        pooled += gathered[:, j]
    out = flat if in_place else flat.copy()               # (a reshape that copied is returned filled all the same)
    out[:, holes] = pooled
    return out.reshape(sums.shape)


def clearance_from_mask(landable: np.ndarray, cell_m: float) -> np.ndarray:
    """Metric distance from each landable cell centre to the nearest point of a non-landable cell.

    The distance transform gives centre-to-centre distance d to the nearest bad cell; the nearest point of
    that cell can be up to half a cell diagonal closer, so d - cell/√2 is a safe lower bound.
    Cells beyond the mask are unknown ground and count as non-landable: a cell at the mask's edge is never
    judged clear of what lies past it (OpenCV's transform ignores the image border, and a confirmed view whose
    landable cells reached the grid's edge put a spot 1.8 m from a car just outside the grid: docs/MEASUREMENTS.md).
    Only the bounding box of the landable cells plus a one-cell non-landable ring is transformed: every cell
    outside it is non-landable (or beyond the mask) and never nearer than the ring cell between (clamping a cell
    onto the box shortens each coordinate difference), so the result is the same as the whole mask's, for a
    fraction of the cost (the grid is 200×200 cells; the landable part is usually a small share of it).
    """
    out = np.zeros(landable.shape, np.float32)
    rows = np.flatnonzero(landable.any(axis=1))
    if rows.size == 0:
        return out
    cols = np.flatnonzero(landable.any(axis=0))
    r0, r1 = int(rows[0]), int(rows[-1]) + 1
    c0, c1 = int(cols[0]), int(cols[-1]) + 1
    box = np.zeros((r1 - r0 + 2, c1 - c0 + 2), bool)     # the ring stays False, past the mask's edge too
    box[1:-1, 1:-1] = landable[r0:r1, c0:c1]
    out[r0:r1, c0:c1] = _clearance(box, cell_m)[1:-1, 1:-1]
    return out


def _clearance(landable: np.ndarray, cell_m: float) -> np.ndarray:
    # A non-landable cell has distance 0, so d·cell - cell/√2 < 0 there and the clamp at 0 zeroes it: no mask
    # pass needed. In place on the transform's own float32 output: no per-frame temporaries.
    dist: np.ndarray = cv2.distanceTransform(landable.view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    # The exact transform's distances are square roots of whole numbers of cells², but OpenCV's float arithmetic
    # leaves up to ~4e-6 cells of error that varies from call to call on the same mask (measured: two
    # different results in 50 identical calls), so replays differed in the last bit of a clearance. Rounding
    # d² to its whole number gives the exact distance, the same every time.
    np.square(dist, out=dist)
    np.rint(dist, out=dist)
    np.sqrt(dist, out=dist)
    np.multiply(dist, np.float32(cell_m), out=dist)
    np.subtract(dist, np.float32(cell_m / math.sqrt(2.0)), out=dist)
    np.maximum(dist, np.float32(0.0), out=dist)
    return dist
