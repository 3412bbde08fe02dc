"""What fusion.motion_grid's GeometryGrid.view computed last, kept for the frames between motion-stage runs
(the geometry arrays do not change then), and the level-step rule it applies. Pure numpy/OpenCV."""
from __future__ import annotations

from typing import Optional

import cv2
import numpy as np


class ViewMemo:
    """What :meth:`GeometryGrid.view` computed last on the unchanged arrays, and on which array cells."""

    def __init__(self) -> None:
        self.box: Optional[tuple[slice, slice]] = None
        # time, oldest single-pair height within the memory then, detectable, high
        self.fused: Optional[tuple[float, float, np.ndarray, np.ndarray]] = None
        self.steps_box: Optional[tuple[slice, slice]] = None
        self.steps: Optional[tuple[np.ndarray, np.ndarray]] = None                # clear, level steps

    def inside(self, g: tuple[slice, slice], steps: bool = False) -> Optional[tuple[slice, slice]]:
        """``g`` relative to the memo's cells, or None when it does not lie within them."""
        box = self.steps_box if steps else self.box
        if box is None:
            return None
        (r, c), (br, bc) = g, box
        if r.start < br.start or r.stop > br.stop or c.start < bc.start or c.stop > bc.stop:
            return None
        return slice(r.start - br.start, r.stop - br.start), slice(c.start - bc.start, c.stop - bc.start)


def _level_steps(down: np.ndarray, max_step_m: float, kernel: np.ndarray) -> np.ndarray:
    """Cells within ``kernel`` of a cell whose surface lies more than ``max_step_m`` higher or lower (NaN: no
    level there).

    Each pair judges heights against its own local ground: a roof measured on its own plane and the street
    measured on the ground's are both clear, and a disc over the roof's edge would hold only clear cells. The
    levels of the surfaces that confirmed nearby cells must agree; a band of cells along every step is left
    unconfirmed, so no clear disc spans one (the kernel reaches over a one-cell gap: a hole-filled cell has
    no level of its own)."""
    finite = np.isfinite(down)
    out: np.ndarray = finite.copy()
    if not finite.any():
        return out
    hi = cv2.dilate(np.where(finite, down, -np.inf).astype(np.float32, copy=False), kernel,
                    borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
    lo = cv2.erode(np.where(finite, down, np.inf).astype(np.float32, copy=False), kernel,
                   borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
    out &= (hi - down > max_step_m) | (down - lo > max_step_m)
    return out


def steps_at_cut_sides(steps: np.ndarray, clear: np.ndarray, down: np.ndarray, cut: tuple[bool, bool, bool, bool],
                       max_step_m: float, kernel: np.ndarray) -> np.ndarray:
    """:func:`_level_steps` of the ``clear`` cells' levels ``down``, given ``steps``: its result on a larger window
    cut down to these cells, where the sides flagged in ``cut`` (top, bottom, left, right) lost clear cells.

    A lost cell reached only the cells within the kernel's half-width of its side; each of those bands is
    recomputed from the band twice as deep (beyond it the cells are this window's own, and its outer side is
    this window's border, as in a whole recomputation), and only its outer half is kept."""
    reach = kernel.shape[0] // 2
    rows, cols = clear.shape
    if min(rows, cols) < 2 * reach:
        return _level_steps(np.where(clear, down, np.nan), max_step_m, kernel)
    out: np.ndarray = steps.copy()
    deep = 2 * reach
    top, bottom, left, right = cut
    for on, band, keep in ((top, np.s_[:deep, :], np.s_[:reach, :]), (bottom, np.s_[-deep:, :], np.s_[-reach:, :]),
                           (left, np.s_[:, :deep], np.s_[:, :reach]), (right, np.s_[:, -deep:], np.s_[:, -reach:])):
        if on:
            out[keep] = _level_steps(np.where(clear[band], down[band], np.nan), max_step_m, kernel)[keep]
    return out
