"""Where the motion stage looks: candidate spots for its window (ARCHITECTURE.md §11), pure numpy + OpenCV.

The stage measures one window per run, centred on one of a few candidate spots: the network's own spot first,
then the best-scoring other cells far enough apart, among the ground a confirmation may use (fusion.confirm:
network-landable, or observed and horizontal by its HVO head); those others alone when the network has no
spot. Drawn from network-landable cells alone, a network whose landable discs all lay on roofs (flow fails
there) kept the window off the streets it called horizontal, and nothing was ever confirmed
(docs/MEASUREMENTS.md, "Where the window may go"). Opt-in: a spot
that geometry has already seen an obstacle beside (within the required clearance) cannot be confirmed by
measuring it again, so neither it nor any other candidate is taken there: the window goes to ground geometry
has not ruled out. Without this a network that keeps proposing a car or a roof's edge (a network trained
elsewhere, or the flat-lying model of benchmarks/lying_model.py) keeps the stage measuring the one spot it
already rejected. Where to look is all this module changes: what confirms a spot is fusion.confirm's rule.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

import cv2
import numpy as np

from edge_landing.runtime.fusion.cells import clearance_from_mask
from edge_landing.runtime.fusion.grid import GridView

if TYPE_CHECKING:
    from edge_landing.runtime.fusion.config import FusionConfig

__all__ = ["KnownObstacles", "acceptable_clearance", "focus_candidates", "ruled_out"]


@dataclass(frozen=True)
class KnownObstacles:
    """Cells where geometry saw an obstacle (``GeometryView.obstacle``), on a grid whose corner cell starts at
    (``north0_m``, ``east0_m``), local NED, cells of the fusion grid's size. A snapshot: never written into."""

    obstacle: np.ndarray
    north0_m: float
    east0_m: float


def ruled_out(view: GridView, known: KnownObstacles, radius_m: float) -> np.ndarray:
    """Cells of ``view`` (bool, its shape) within ``radius_m`` of a known obstacle: a disc of that radius centred
    there would hold it. ``known`` may lie on an earlier position of the grid (it moves by whole cells)."""
    rows, cols = view.shape
    dr = int(round((known.north0_m - view.north0_m) / view.cell_m))   # known cell (r, c) is view cell (r+dr, c+dc)
    dc = int(round((known.east0_m - view.east0_m) / view.cell_m))
    src = known.obstacle
    shifted = np.zeros((rows, cols), np.uint8)
    r0, r1 = max(0, dr), min(rows, src.shape[0] + dr)
    c0, c1 = max(0, dc), min(cols, src.shape[1] + dc)
    if r0 >= r1 or c0 >= c1:
        return shifted.astype(bool)
    shifted[r0:r1, c0:c1] = src[r0 - dr:r1 - dr, c0 - dc:c1 - dc]
    reach = int(math.ceil(radius_m / view.cell_m))
    if reach == 0 or not shifted.any():
        return shifted.astype(bool)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1, 2 * reach + 1))
    return np.asarray(cv2.dilate(shifted, disc), bool)


def focus_candidates(view: GridView, first: Optional[np.ndarray], here_ne: tuple[float, float], config: FusionConfig,
                     count: int = 3, separation_m: float = 10.0, known: Optional[KnownObstacles] = None,
                     use_hvo: bool = False) -> Optional[np.ndarray]:
    """Up to ``count`` spots (K×3 NED or grid frame) for the motion stage's window: ``first`` (the network's
    spot), then the best-scoring others at least ``separation_m`` from those already taken, among the discs of
    ground a confirmation may use (:func:`acceptable_clearance`). The stage measures where a keyframe sees best
    (fusion.motion), so ground off the vehicle's line of flight gets measured too. With ``known`` obstacles (on
    the same frame as ``view``) and ``config.focus_skip_obstacles_m`` >= 0 (negative: off, the default), no
    candidate is taken within that many metres of one (0: on one), ``first`` included; when that leaves none,
    ``first`` alone. ``first`` None (the network has no landable disc of its own): the others alone, or None
    when there are none (the stage then scans)."""
    need, skip_m = config.required_clearance_m, config.focus_skip_obstacles_m
    blocked = None if known is None or skip_m < 0 else ruled_out(view, known, skip_m)
    out: list[np.ndarray] = []
    cell = None if first is None else view.cell_of(float(first[0]), float(first[1]))
    if first is not None and (blocked is None or cell is None or not blocked[cell]):
        out.append(np.asarray(first, np.float64))
    clearance = acceptable_clearance(view, config, use_hvo)
    flat = clearance.ravel() >= need - 1e-6
    if blocked is not None:
        flat &= ~blocked.ravel()
    idx = np.flatnonzero(flat)
    if idx.size and count > len(out):
        out += _spread_picks(view, clearance, idx, here_ne, config, count - len(out), separation_m, out,
                             math.nan if first is None else float(first[2]))
    if out:
        return np.stack(out)
    return None if first is None else np.asarray(first, np.float64)[None, :]


def acceptable_clearance(view: GridView, config: FusionConfig, use_hvo: bool) -> np.ndarray:
    """Clearance (m, the grid's shape) of the ground a confirmation may use: cells the network does not object
    to (``GridView.allowed_in``, fusion.confirm's rule: landable, or observed and horizontal by an HVO head),
    not only its landable ones. Where that adds no cell, the view's own clearance (the same distances)."""
    allowed = view.allowed_in((slice(None), slice(None)), config.horizontal_share_to_confirm(use_hvo))
    if not np.any(allowed & ~view.landable):
        return view.clearance_m
    return clearance_from_mask(allowed, view.cell_m)


def _spread_picks(view: GridView, clearance: np.ndarray, idx: np.ndarray, here_ne: tuple[float, float],
                  config: FusionConfig, count: int, separation_m: float, taken: list[np.ndarray], down_m: float
                  ) -> list[np.ndarray]:
    """Greedy in score order (ties: grid order), vectorised: each pick is the best cell of ``idx`` still
    ``separation_m`` from every spot taken; thousands of landable cells would otherwise be walked one by one.
    A pick's level is its cell's, else ``down_m`` (the network's spot's); a pick with neither is skipped."""
    rows = idx // view.shape[1]                  # (np.divmod and np.hypot are several times slower)
    cols = idx - rows * view.shape[1]
    north = view.north0_m + (rows + 0.5) * view.cell_m
    east = view.east0_m + (cols + 0.5) * view.cell_m
    score = np.minimum(clearance.ravel()[idx], config.clearance_saturation_m) \
        - config.travel_penalty_per_m * np.sqrt(np.square(north - here_ne[0]) + np.square(east - here_ne[1]))
    free = np.ones(idx.size, dtype=bool)
    for spot in taken:
        free &= np.square(north - spot[0]) + np.square(east - spot[1]) >= separation_m * separation_m
    picks: list[np.ndarray] = []
    for _ in range(count):
        if not free.any():
            break
        i = int(np.argmax(np.where(free, score, -np.inf)))
        down, _, _ = view.cell_stats(int(rows[i]), int(cols[i]))
        level = down if math.isfinite(down) else down_m
        if not math.isfinite(level):
            free[i] = False
            continue
        picks.append(np.array([north[i], east[i], level]))
        free &= np.square(north - north[i]) + np.square(east - east[i]) >= separation_m * separation_m
    return picks
