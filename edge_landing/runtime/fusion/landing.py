"""Choosing the landing spot on the fused grid (ARCHITECTURE.md §6 step 6).

Candidates are cells whose clearance reaches the vehicle radius plus the margin. Score (metres) =
min(clearance, saturation) - travel_penalty_per_m × horizontal distance from the vehicle, so beyond the
saturation a wider clear area no longer beats a nearer one. The spot kept from earlier frames stays while
it is still a candidate and the best new score does not beat it by more than ``hysteresis_m``: the
target does not jump between near-equal spots from frame to frame.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional, Tuple, overload

import numpy as np

from edge_landing.runtime.fusion.grid import GridView

if TYPE_CHECKING:   # fuser imports this module: the config type is for the checker only
    from edge_landing.runtime.fusion.fuser import FusionConfig


@dataclass(frozen=True)
class KeptSpot:
    """The previous target, in the grid's frame (metres) and its capture time."""

    north_m: float
    east_m: float
    time_s: float


@dataclass(frozen=True)
class Choice:
    """The chosen spot, in the grid's frame: position, clearance, score and the evidence of its cell."""

    north_m: float
    east_m: float
    down_m: float
    clearance_m: float
    score: float
    horizontal_share: float
    flat_share: float
    kept: bool


@overload
def _score(clearance_m: float, travel_m: float, config: FusionConfig) -> float: ...
@overload
def _score(clearance_m: np.ndarray, travel_m: np.ndarray, config: FusionConfig) -> np.ndarray: ...
def _score(clearance_m: float | np.ndarray, travel_m: float | np.ndarray,
           config: FusionConfig) -> float | np.ndarray:
    score: float | np.ndarray = (np.minimum(clearance_m, config.clearance_saturation_m)
                                 - config.travel_penalty_per_m * travel_m)
    return score


_NEAR_M = 10.0     # with many candidates, the best spot is looked for within this distance (each axis) first
_MANY = 1000


def _best(view: GridView, here_ne: Tuple[float, float], config: FusionConfig, clearance: np.ndarray,
          flat_idx: np.ndarray, row0: int = 0, col0: int = 0) -> tuple[int, int, float, float, float]:
    """(row, col, north, east, score) of the best-scoring candidate ``flat_idx`` (flat indices, grid order) of
    ``clearance``, a block of the grid's cells from (row0, col0); the first in grid order on ties."""
    rows_i, cols_i = np.divmod(flat_idx, clearance.shape[1])
    rows_i += row0
    cols_i += col0
    north = view.north0_m + (rows_i + 0.5) * view.cell_m
    east = view.east0_m + (cols_i + 0.5) * view.cell_m
    dn, de = north - here_ne[0], east - here_ne[1]
    clear_c = clearance.ravel()[flat_idx]
    # np.hypot is several times slower than sqrt(dn² + de²), which is within a few ulp of it: only candidates
    # within a (far wider) hair of the best rough score can have the best exact score, so only they get hypot.
    # The subset keeps grid order, so ties still go to the first cell.
    rough = _score(clear_c, np.sqrt(dn * dn + de * de), config)
    top = float(rough.max())
    near = np.flatnonzero(rough >= top - 1e-9 * (1.0 + config.clearance_saturation_m + abs(top)))
    scores = _score(clear_c[near], np.hypot(dn[near], de[near]), config)
    best = int(near[int(np.argmax(scores))])
    return int(rows_i[best]), int(cols_i[best]), float(north[best]), float(east[best]), float(scores.max())


def _near(view: GridView, here_ne: Tuple[float, float], reach_m: float) -> tuple[slice, slice]:
    """The cells whose centre is within ``reach_m`` of ``here_ne`` along each axis (computed as in :func:`_best`)."""
    rows, cols = view.shape
    dn = np.abs(view.north0_m + (np.arange(rows) + 0.5) * view.cell_m - here_ne[0])
    de = np.abs(view.east0_m + (np.arange(cols) + 0.5) * view.cell_m - here_ne[1])
    r, c = np.flatnonzero(dn <= reach_m), np.flatnonzero(de <= reach_m)
    if r.size == 0 or c.size == 0:
        return slice(0, 0), slice(0, 0)
    return slice(int(r[0]), int(r[-1]) + 1), slice(int(c[0]), int(c[-1]) + 1)


def _best_near(view: GridView, here_ne: Tuple[float, float], config: FusionConfig
               ) -> Optional[tuple[int, int, float, float, float]]:
    """:func:`_best` over the whole grid when it lies near the vehicle, else None.

    A cell beyond _NEAR_M along an axis is farther than that (hypot >= each |axis|, rounding is monotone), so it
    scores at most saturation - penalty·_NEAR_M (float32 saturation: the clearance is float32). When the best
    near score beats that bound by more than any rounding, every cell with the best score is near, and the
    near block's row-major order is the grid's: the same cell, score and tie-breaking."""
    rows, cols = _near(view, here_ne, _NEAR_M)
    block = view.clearance_m[rows, cols]
    idx = np.flatnonzero(block.ravel() >= config.required_clearance_m - 1e-6)
    if idx.size == 0:
        return None
    best = _best(view, here_ne, config, block, idx, rows.start, cols.start)
    sat = max(config.clearance_saturation_m, float(np.float32(config.clearance_saturation_m)))
    bound = sat - config.travel_penalty_per_m * _NEAR_M
    return best if best[4] > bound + 1e-9 * (1.0 + abs(bound)) else None


def choose_spot(view: GridView, here_ne: Tuple[float, float], config: FusionConfig, kept: Optional[KeptSpot] = None
                ) -> Optional[Choice]:
    """Best spot on ``view`` for a vehicle at ``here_ne`` (north, east in the grid's frame), or None.

    ``config`` is a FusionConfig (required_clearance_m, clearance_saturation_m, travel_penalty_per_m,
    hysteresis_m are used).
    """
    need = config.required_clearance_m
    clearance = view.clearance_m
    flat_idx = np.flatnonzero(clearance.ravel() >= need - 1e-6)
    if flat_idx.size == 0:
        return None
    best = _best_near(view, here_ne, config) if flat_idx.size > _MANY else None
    if best is None:
        best = _best(view, here_ne, config, clearance, flat_idx)
    r, c = best[0], best[1]
    pick = (best[2], best[3], best[4], False)

    if kept is not None:
        cell = view.cell_of(kept.north_m, kept.east_m)
        if cell is not None and clearance[cell] >= need - 1e-6:
            kept_travel = math.hypot(kept.north_m - here_ne[0], kept.east_m - here_ne[1])
            kept_score = float(_score(clearance[cell], kept_travel, config))
            if kept_score + config.hysteresis_m >= pick[2]:
                r, c = cell
                pick = (kept.north_m, kept.east_m, kept_score, True)
    down_m, horizontal_share, flat_share = view.cell_stats(r, c)
    return Choice(north_m=pick[0], east_m=pick[1], down_m=down_m, clearance_m=float(clearance[r, c]),
                  score=pick[2], horizontal_share=horizontal_share, flat_share=flat_share, kept=pick[3])
