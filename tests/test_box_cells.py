"""benchmarks.narrow_obstacles.BoxCells: what geometry said about every box, read from fusion's grid cells."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from edge_landing.benchmarks.narrow_obstacles import BoxCells
from edge_landing.runtime.fusion.grid_view import GridView
from edge_landing.runtime.fusion.motion_grid import GeometryView


def _frame(clear_cells=(), obstacle_cells=(), measured_to_m: float = 0.3, north0_m: float = -2.0):
    """A fuser after one frame: a 8×8 grid of 0.5 m cells from (north0, -2 m), everything measured to
    ``measured_to_m``, the given (row, col) cells clear or obstacles."""
    shape = (8, 8)
    clear, obstacle = np.zeros(shape, bool), np.zeros(shape, bool)
    for rc in clear_cells:
        clear[rc] = True
    for rc in obstacle_cells:
        obstacle[rc] = True
    geo = GeometryView(0.0, 0.5, clear, obstacle, np.full(shape, measured_to_m, np.float32), np.full(shape, 10.0),
                       np.zeros(shape), np.zeros(shape))
    grid = GridView("ned", 0.5, north0_m, -2.0, 0.0, np.zeros((5, *shape)), np.zeros(shape, bool),
                    np.zeros(shape, np.float32))
    return SimpleNamespace(geometry=geo, grid=grid)


def test_boxes_are_counted_by_the_cell_holding_their_centre_over_the_whole_pass():
    boxes = BoxCells(np.array([[0.1, 0.1], [1.1, -1.9], [30.0, 0.0]]), obstacle_height_m=0.5)   # the last: off-grid
    boxes.add(_frame(clear_cells=[(4, 4)]))                 # box 0's cell: (0.1 + 2) / 0.5 -> row 4, col 4
    boxes.add(_frame(obstacle_cells=[(6, 0)]))              # box 1's: row 6, col 0
    boxes.add(_frame(clear_cells=[(4, 4)], north0_m=-1.5))  # the grid moved: box 0 is now in row 3, not clear
    boxes.add(SimpleNamespace(geometry=None, grid=None))    # a frame without geometry says nothing
    assert boxes.counts() == {"measured": 2, "confirmed_clear": 1, "marked_obstacle": 1}


def test_a_box_measured_too_coarsely_is_not_counted():
    boxes = BoxCells(np.array([[0.1, 0.1]]), obstacle_height_m=0.5)
    boxes.add(_frame(clear_cells=[(4, 4)], measured_to_m=2.0))
    assert boxes.counts() == {"measured": 0, "confirmed_clear": 0, "marked_obstacle": 0}
