"""Where the motion stage looks (fusion.focus): not again where geometry already saw an obstacle."""
from __future__ import annotations

import numpy as np

from edge_landing.runtime.fusion.config import FusionConfig
from edge_landing.runtime.fusion.focus import KnownObstacles, focus_candidates, ruled_out
from edge_landing.runtime.fusion.grid import GridView


def _everything_landable(size: int = 40, cell_m: float = 1.0, north0_m: float = 0.0, east0_m: float = 0.0) -> GridView:
    """A network that calls every cell landable with saturated clearance (the flat-lying model)."""
    clearance = np.full((size, size), 10.0, np.float32)
    sums = np.zeros((5, size, size))
    sums[0], sums[1] = 1.0, 2.0                       # every cell observed once, 2 m down
    return GridView("ned", cell_m, north0_m, east0_m, 0.0, sums, clearance > 0, clearance)


def test_known_obstacles_rule_out_the_disc_around_them_on_a_moved_grid():
    view = _everything_landable(north0_m=3.0, east0_m=-2.0)        # the grid moved by (3, -2) cells since
    obstacle = np.zeros((40, 40), bool)
    obstacle[10, 10] = True                                         # at north 10.5, east 10.5 on the old grid
    out = ruled_out(view, KnownObstacles(obstacle, 0.0, 0.0), radius_m=2.0)
    rows, cols = np.nonzero(out)
    assert out[7, 12] and out[7 + 2, 12] and out[7, 12 - 2] and not out[7 + 3, 12] and not out[7 + 2, 12 + 2]
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (5, 9, 10, 14)   # the same place in NED
    far = ruled_out(view, KnownObstacles(obstacle, 500.0, 0.0), radius_m=2.0)  # no overlap with this grid
    assert not far.any()


def test_the_networks_spot_beside_a_known_obstacle_gives_its_window_to_other_ground():
    config = FusionConfig(focus_skip_obstacles_m=FusionConfig().required_clearance_m)
    view = _everything_landable()
    first = np.array([20.5, 20.5, 2.0])
    without = focus_candidates(view, first, (0.0, 0.0), config)
    np.testing.assert_allclose(without[0], first)                  # nothing known: the network's spot first
    obstacle = np.zeros((40, 40), bool)
    obstacle[21, 20] = obstacle[0:3, 0:3] = True                    # beside the spot, and at the best other cell
    picks = focus_candidates(view, first, (0.0, 0.0), config, known=KnownObstacles(obstacle, 0.0, 0.0))
    assert len(picks) == 3
    blocked = ruled_out(view, KnownObstacles(obstacle, 0.0, 0.0), config.required_clearance_m)
    for north, east, _ in picks:
        assert not blocked[int(north), int(east)], (north, east)    # none within the clearance of an obstacle
    assert not np.any(np.all(np.isclose(picks, first), axis=1))     # the rejected spot is not measured again
    gaps = [np.hypot(*(a[:2] - b[:2])) for i, a in enumerate(picks) for b in picks[i + 1:]]
    assert min(gaps) >= 10.0


def test_a_radius_of_zero_skips_only_the_obstacles_own_cells():
    view = _everything_landable()
    obstacle = np.zeros((40, 40), bool)
    obstacle[20, 20] = True
    np.testing.assert_array_equal(ruled_out(view, KnownObstacles(obstacle, 0.0, 0.0), 0.0), obstacle)
    config = FusionConfig(focus_skip_obstacles_m=0.0)
    first = np.array([20.5, 20.5, 2.0])                             # on the obstacle: not measured again
    picks = focus_candidates(view, first, (0.0, 0.0), config, known=KnownObstacles(obstacle, 0.0, 0.0))
    assert not np.any(np.all(np.isclose(picks, first), axis=1)) and len(picks) == 3
    beside = np.array([21.5, 20.5, 2.0])                            # beside it: still the first candidate
    np.testing.assert_allclose(focus_candidates(view, beside, (0.0, 0.0), config,
                                                known=KnownObstacles(obstacle, 0.0, 0.0))[0], beside)


def test_skipping_known_obstacles_is_opt_in():
    config = FusionConfig()
    assert config.focus_skip_obstacles_m < 0
    view, first = _everything_landable(), np.array([20.5, 20.5, 2.0])
    obstacle = np.zeros((40, 40), bool)
    obstacle[20, 20] = True
    np.testing.assert_array_equal(focus_candidates(view, first, (0.0, 0.0), config,
                                                   known=KnownObstacles(obstacle, 0.0, 0.0)),
                                  focus_candidates(view, first, (0.0, 0.0), config))


def test_when_everything_is_ruled_out_the_networks_spot_is_kept():
    config = FusionConfig(focus_skip_obstacles_m=2.0)
    view = _everything_landable(size=10)
    first = np.array([5.5, 5.5, 2.0])
    picks = focus_candidates(view, first, (0.0, 0.0), config, known=KnownObstacles(np.ones((10, 10), bool), 0.0, 0.0))
    np.testing.assert_allclose(picks, [first])


def test_a_skip_radius_that_is_not_a_number_is_refused():
    import math

    import pytest

    from edge_landing.runtime.core.errors import InputError

    for bad in (math.nan, math.inf, -math.inf, 1e9):
        with pytest.raises(InputError, match="focus_skip_obstacles_m"):
            FusionConfig(focus_skip_obstacles_m=bad)


def test_the_window_may_go_to_ground_a_confirmation_would_accept_not_only_to_network_landable_ground():
    """A network whose landable discs are all on one roof (a network trained elsewhere) but which calls the
    streets horizontal: confirmation accepts geometry-clear horizontal ground (fusion.confirm), so the window
    must be able to go there, or the stage keeps measuring the roof, where the flow fails, and nothing is ever
    confirmed (the shipped model on urban 1505 and 7202 sent no target before)."""
    from edge_landing.runtime.fusion.cells import clearance_from_mask

    size = 40
    sums = np.zeros((5, size, size))
    sums[0], sums[1], sums[3] = 1.0, 2.0, 1.0          # every cell observed once, 2 m down, horizontal
    landable = np.zeros((size, size), bool)
    landable[2:10, 2:10] = True                         # the roof: the only network-landable ground
    view = GridView("ned", 1.0, 0.0, 0.0, 0.0, sums, landable, clearance_from_mask(landable, 1.0))
    first = np.array([5.5, 5.5, 2.0])                   # the network's spot, on the roof
    config = FusionConfig()
    roof_only = focus_candidates(view, first, (0.0, 0.0), config, use_hvo=False)
    np.testing.assert_allclose(roof_only, [first])      # nothing else landable lies 10 m from the spot
    picks = focus_candidates(view, first, (0.0, 0.0), config, use_hvo=True)
    np.testing.assert_allclose(picks[0], first)         # the network's spot still comes first
    assert len(picks) == 3
    for north, east, _ in picks[1:]:
        assert not landable[int(north), int(east)] and np.hypot(north - first[0], east - first[1]) >= 10.0
    off = focus_candidates(view, first, (0.0, 0.0), FusionConfig(confirm_on_horizontal=False), use_hvo=True)
    np.testing.assert_allclose(off, roof_only)          # confirmation takes landable ground only: so does the window
    sums[3] = 0.0                                       # streets the network does not call horizontal
    np.testing.assert_allclose(focus_candidates(view, first, (0.0, 0.0), config, use_hvo=True), roof_only)


def test_with_no_network_spot_the_window_still_goes_where_a_confirmation_could_come_from():
    """A network with no landable disc of its own that calls the ground horizontal (the shipped model on urban
    9749 once it was past its spot: 'no safe spot' on most frames): confirmation accepts geometry-clear horizontal
    ground, so the window goes there instead of scanning blind. With nothing acceptable, None: the stage scans."""
    from edge_landing.runtime.fusion.cells import clearance_from_mask

    size = 40
    sums = np.zeros((5, size, size))
    sums[0], sums[1], sums[3] = 1.0, 2.0, 1.0          # every cell observed once, 2 m down, horizontal
    landable = np.zeros((size, size), bool)             # ... and none landable by the network's own rules
    view = GridView("ned", 1.0, 0.0, 0.0, 0.0, sums, landable, clearance_from_mask(landable, 1.0))
    picks = focus_candidates(view, None, (20.0, 20.0), FusionConfig(), use_hvo=True)
    assert picks is not None and picks.shape == (3, 3)
    np.testing.assert_allclose(picks[:, 2], 2.0)        # each at its cell's level
    for i in range(3):
        assert 1.0 <= picks[i, 0] <= size - 1.0 and 1.0 <= picks[i, 1] <= size - 1.0   # inside the observed ground
        for j in range(i):
            assert np.hypot(*(picks[i, :2] - picks[j, :2])) >= 10.0
    assert focus_candidates(view, None, (20.0, 20.0), FusionConfig(), use_hvo=False) is None   # no HVO head
    sums[3] = 0.0                                       # nothing horizontal either
    assert focus_candidates(view, None, (20.0, 20.0), FusionConfig(), use_hvo=True) is None
