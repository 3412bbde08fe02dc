"""The network's last word on each local NED cell, kept as long as geometry's confirmations (ARCHITECTURE.md §11).

A spot is confirmed where geometry found it clear and the network does not object. Fusion's grid forgets a
cell ``memory_s`` (3 s) after the camera last saw it, while a geometry confirmation holds for
``geometry_memory_s`` (30 s): the camera looks ahead, so by the time a hover's or a descent's pairs have
measured a patch of ground to the obstacle height, the network often no longer sees it, and the patch could
never be confirmed (measured: urban seed 3579, whose only fully clear discs were all out of the network's
view, docs/MEASUREMENTS.md). This keeps, per cell, the time the network last saw it and did not object;
a look that objects wipes it at once. So the network still vetoes what it sees now, and a verdict it can no
longer renew lasts no longer than the geometry beside it.

Cells follow fusion's grid (same size and origin, whole-cell moves). Local NED only (with a telemetry
position): a vehicle-centred grid's cells are not the same ground from frame to frame.
Pure numpy; memory: one grid-sized array.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from edge_landing.runtime.fusion.grid_view import GridView, Window


class NetworkVerdicts:
    """When the network last saw each cell of fusion's NED grid and did not object (``-inf``: never, or it
    objected at its last look)."""

    def __init__(self, memory_s: float):
        self.memory_s = float(memory_s)
        self.clear()

    def clear(self) -> None:
        self._ok_t: Optional[np.ndarray] = None
        self._origin = (math.nan, math.nan)      # north0, east0 of the grid ``_ok_t`` is on
        self._time_s = -math.inf

    def update(self, view: GridView, win: Window, allowed: np.ndarray, now_s: float) -> None:
        """Record this frame's verdicts: ``allowed`` (the network does not object) on the cells ``win`` of
        ``view``, which must hold every cell ``view`` observes (an objection outside it would be missed)."""
        shape = view.landable.shape
        old = self._ok_t
        if old is None or old.shape != shape or now_s < self._time_s:
            ok_t = np.full(shape, -np.inf)          # (time went back: nothing older is trusted)
        else:
            ok_t = self._moved(old, view)
        self._ok_t, self._origin, self._time_s = ok_t, (view.north0_m, view.east0_m), now_s
        here, seen = ok_t[win], view.observed_in(win)
        np.putmask(here, seen, -np.inf)             # (putmask: a fraction of boolean-index assignment's time)
        np.putmask(here, seen & allowed, now_s)

    def _moved(self, old: np.ndarray, view: GridView) -> np.ndarray:
        """``old`` on ``view``'s cells (the grid moves by whole cells; cells new to it: never seen)."""
        dr = int(round((view.north0_m - self._origin[0]) / view.cell_m))
        dc = int(round((view.east0_m - self._origin[1]) / view.cell_m))
        if dr == 0 and dc == 0:
            return old
        rows, cols = old.shape
        new = np.full(old.shape, -np.inf)
        r0, r1, c0, c1 = max(dr, 0), min(rows + dr, rows), max(dc, 0), min(cols + dc, cols)
        if r0 < r1 and c0 < c1:                      # view cell (r, c) was old cell (r + dr, c + dc)
            new[r0 - dr:r1 - dr, c0 - dc:c1 - dc] = old[r0:r1, c0:c1]
        return new

    def allowed_in(self, win: Window, now_s: float) -> np.ndarray:
        """Cells of ``win`` (on the grid of the last :meth:`update`) whose last look by the network, within
        ``memory_s`` of ``now_s``, did not object."""
        if self._ok_t is None:
            return np.zeros((win[0].stop - win[0].start, win[1].stop - win[1].start), bool)
        return np.asarray(now_s - self._ok_t[win] <= self.memory_s)

    def age_s(self, cell: tuple[int, int], now_s: float) -> float:
        """Time since the network last saw ``cell`` and did not object (inf: never, or it objected)."""
        return math.inf if self._ok_t is None else float(now_s - self._ok_t[cell])
