"""The read-only snapshot of fusion's top-down grid (edge_landing.runtime.fusion.grid), pure numpy."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

Window = tuple[slice, slice]
_ALL: Window = (slice(None), slice(None))


@dataclass(frozen=True)
class GridView:
    """A read-only snapshot of the grid for overlays, selection and tests.

    Rows run along north, columns along east. ``frame`` is ``"ned"`` when the grid is kept in local NED
    (cell centres and heights are absolute local positions) or ``"vehicle"`` for a level, vehicle-centred
    grid (NED-oriented, origin at the camera). Per-cell statistics are computed on access (overlays only
    need them sometimes; the per-frame path reads single cells through :meth:`cell_stats`).
    """

    frame: str
    cell_m: float
    north0_m: float
    east0_m: float
    ref_down_m: float          # heights in ``sums`` are relative to this
    sums: np.ndarray           # 5 × rows × cols: count, Σh, Σh², Σ horizontal votes, Σ flat votes (NED:
                               # summed over frames, so spread_m there mixes frames; landable uses votes)
    landable: np.ndarray       # rows × cols bool
    clearance_m: np.ndarray    # rows × cols float32, 0 where not landable
    votes: Optional[np.ndarray] = None   # 2 × rows × cols: (decayed) frames that observed / judged landable
    seen: Optional[np.ndarray] = None    # rows × cols: exp(-time since last observed / decay_s)
    min_seen_weight: float = 0.0

    @property
    def observed(self) -> np.ndarray:
        """rows × cols bool: cells observed recently enough to count (time-bounded memory)."""
        return self.observed_in(_ALL)

    def observed_in(self, win: Window) -> np.ndarray:
        """:attr:`observed` on the cells ``win`` (rows, columns)."""
        if self.seen is None:
            return np.asarray(self.sums[0][win] > 0)
        return np.asarray(self.seen[win] >= self.min_seen_weight)

    def allowed_in(self, win: Window, min_horizontal_share: Optional[float] = None) -> np.ndarray:
        """Cells of ``win`` the network does not object to: landable, or, given ``min_horizontal_share`` (an HVO
        head whose class may stand in for the network's own flatness tests: fusion.confirm), observed with at
        least that mean P(horizontal)."""
        allowed: np.ndarray = self.landable[win]
        if min_horizontal_share is not None:
            # The share without horizontal_share_in's NaN fill (0/0 is NaN anyway, and NaN >= x is False): a
            # third of its time on a box of most of the grid.
            with np.errstate(invalid="ignore", divide="ignore"):
                horizontal = self.sums[3][win] / self.sums[0][win] >= min_horizontal_share
            allowed = allowed | (self.observed_in(win) & horizontal)
        return allowed

    @property
    def shape(self) -> tuple[int, ...]:
        return self.landable.shape

    @property
    def count(self) -> np.ndarray:
        count: np.ndarray = self.sums[0].astype(np.float32)
        return count

    def _mean(self, k: int, win: Window = _ALL) -> np.ndarray:
        count = self.sums[0][win]
        with np.errstate(invalid="ignore", divide="ignore"):
            mean: np.ndarray = np.where(count > 0, self.sums[k][win] / count, np.nan).astype(np.float32)
            return mean

    @property
    def height_m(self) -> np.ndarray:
        """Mean down coordinate of each cell (NaN where unobserved)."""
        height_m: np.ndarray = self._mean(1) + np.float32(self.ref_down_m)
        return height_m

    @property
    def spread_m(self) -> np.ndarray:
        mean = self._mean(1)
        spread_m: np.ndarray = np.sqrt(np.maximum(self._mean(2) - mean * mean, 0.0))
        return spread_m

    @property
    def horizontal_share(self) -> np.ndarray:
        return self._mean(3)

    def horizontal_share_in(self, win: Window) -> np.ndarray:
        """:attr:`horizontal_share` on the cells ``win`` (rows, columns)."""
        return self._mean(3, win)

    @property
    def flat_share(self) -> np.ndarray:
        return self._mean(4)

    def cell_stats(self, row: int, col: int) -> tuple[float, float, float]:
        """(down_m, horizontal_share, flat_share) of one observed cell."""
        c = float(self.sums[0, row, col])
        return (float(self.sums[1, row, col]) / c + self.ref_down_m, float(self.sums[3, row, col]) / c,
                float(self.sums[4, row, col]) / c)

    def cell_centres_m(self) -> np.ndarray:
        """rows×cols×2 array of (north, east) cell centres in metres, in this grid's frame."""
        rows, cols = self.shape
        north = self.north0_m + (np.arange(rows) + 0.5) * self.cell_m
        east = self.east0_m + (np.arange(cols) + 0.5) * self.cell_m
        out = np.empty((rows, cols, 2), dtype=np.float64)
        out[..., 0] = north[:, None]
        out[..., 1] = east[None, :]
        return out

    def cell_of(self, north_m: float, east_m: float) -> Optional[tuple[int, int]]:
        """(row, col) of the cell holding a point, or None outside the grid."""
        r = int(math.floor((north_m - self.north0_m) / self.cell_m))
        c = int(math.floor((east_m - self.east0_m) / self.cell_m))
        rows, cols = self.shape
        return (r, c) if 0 <= r < rows and 0 <= c < cols else None
