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


def choose_spot(view: GridView, here_ne: Tuple[float, float], config: FusionConfig, kept: Optional[KeptSpot] = None
                ) -> Optional[Choice]:
    """Best spot on ``view`` for a vehicle at ``here_ne`` (north, east in the grid's frame), or None.

    ``config`` is a FusionConfig (required_clearance_m, clearance_saturation_m, travel_penalty_per_m,
    hysteresis_m are used).
    """
    need = config.required_clearance_m
    clearance = view.clearance_m
    flat_idx = np.flatnonzero(clearance >= need - 1e-6)      # (1-D: np.nonzero of a 2-D mask is several times slower)
    if flat_idx.size == 0:
        return None
    n_cols = view.shape[1]
    rows_i = flat_idx // n_cols                             # (np.divmod is several times slower)
    cols_i = flat_idx - rows_i * n_cols
    d_north = view.north0_m + (rows_i + 0.5) * view.cell_m - here_ne[0]
    d_east = view.east0_m + (cols_i + 0.5) * view.cell_m - here_ne[1]
    travel = np.sqrt(d_north * d_north + d_east * d_east)     # (np.hypot: 3x slower, and no overflow to guard)
    scores = _score(np.take(clearance.ravel(), flat_idx), travel, config)
    best = int(np.argmax(scores))
    r, c = int(rows_i[best]), int(cols_i[best])
    pick = (view.north0_m + (r + 0.5) * view.cell_m, view.east0_m + (c + 0.5) * view.cell_m, float(scores[best]), False)

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
