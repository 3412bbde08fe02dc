"""The network's last look at each local NED cell, kept as long as geometry's confirmations (fusion.verdicts):
ground that geometry clears after the camera has looked past it can be confirmed, an objection at the last
look still vetoes, and nothing outlives the memory or a move of the grid."""
from __future__ import annotations

from typing import Optional

import numpy as np

from edge_landing.runtime.core.camera import Intrinsics, Mount
from edge_landing.runtime.fusion.confirm import GeometryConfirmation
from edge_landing.runtime.fusion.fuser import FusionConfig
from edge_landing.runtime.fusion.grid_view import GridView
from edge_landing.runtime.fusion.motion_grid import GeometryView
from edge_landing.runtime.fusion.verdicts import NetworkVerdicts

CELL_M = 0.5
SHAPE = (40, 40)
ALL = (slice(0, SHAPE[0]), slice(0, SHAPE[1]))


def _view(seen_rows: slice, landable_rows: Optional[slice] = None, north0_m: float = 0.0, frame: str = "ned",
          horizontal: float = 1.0, held_rows: slice = slice(0, SHAPE[0])) -> GridView:
    """A fusion grid that observes rows ``seen_rows`` (all columns), network-landable on ``landable_rows``
    (default: all it observes), HVO ``horizontal`` share there; it holds (decayed) sums on ``held_rows``."""
    seen = np.zeros(SHAPE, np.float32)
    seen[seen_rows] = 1.0
    landable = np.zeros(SHAPE, bool)
    landable[seen_rows if landable_rows is None else landable_rows] = True
    landable &= seen > 0
    sums = np.zeros((5,) + SHAPE, np.float32)
    sums[0, held_rows] = 0.01
    sums[0][seen > 0] = 1.0
    sums[3] = sums[0] * horizontal
    sums[4] = sums[0]
    return GridView(frame, CELL_M, north0_m, 0.0, 0.0, sums, landable, np.zeros(SHAPE, np.float32), None, seen,
                    0.5)


def test_a_cell_keeps_the_networks_last_verdict_for_the_memory_and_no_longer():
    verdicts = NetworkVerdicts(memory_s=30.0)
    first = _view(slice(20, 40))
    verdicts.update(first, ALL, first.landable, now_s=0.0)
    later = _view(slice(0, 20))                    # the camera looks elsewhere now
    verdicts.update(later, ALL, later.landable, now_s=10.0)
    kept = verdicts.allowed_in(ALL, 10.0)
    assert kept[0:20].all() and kept[20:40].all()  # seen now, and seen 10 s ago
    assert verdicts.age_s((30, 5), 10.0) == 10.0
    verdicts.update(later, ALL, later.landable, now_s=30.5)
    gone = verdicts.allowed_in(ALL, 30.5)
    assert gone[0:20].all() and not gone[20:40].any()   # 30.5 s since the network last saw rows 20-39


def test_an_objection_at_the_last_look_wipes_an_earlier_verdict_at_once():
    verdicts = NetworkVerdicts(memory_s=30.0)
    first = _view(slice(0, 40))
    verdicts.update(first, ALL, first.landable, now_s=0.0)
    objecting = _view(slice(0, 40), landable_rows=slice(0, 10))   # rows 10-39: not landable any more
    verdicts.update(objecting, ALL, objecting.landable, now_s=1.0)
    away = _view(slice(0, 5))
    verdicts.update(away, ALL, away.landable, now_s=2.0)
    kept = verdicts.allowed_in(ALL, 2.0)
    assert kept[0:10].all() and not kept[10:40].any()
    assert verdicts.age_s((20, 0), 2.0) == float("inf")


def test_verdicts_stay_on_their_ground_when_the_grid_moves_and_time_going_back_forgets_them():
    verdicts = NetworkVerdicts(memory_s=30.0)
    first = _view(slice(10, 12))                   # ground rows 10-11: north 5.0-6.0 m
    verdicts.update(first, ALL, first.landable, now_s=0.0)
    moved = _view(slice(0, 0), north0_m=2.0)       # the grid moved 4 cells north, sees nothing
    verdicts.update(moved, ALL, moved.landable, now_s=1.0)
    kept = verdicts.allowed_in(ALL, 1.0)
    assert np.flatnonzero(kept.any(axis=1)).tolist() == [6, 7]   # the same ground: north 5.0-6.0 m
    back = _view(slice(0, 0), north0_m=2.0)
    verdicts.update(back, ALL, back.landable, now_s=0.5)             # time went back: nothing older is trusted
    assert not verdicts.allowed_in(ALL, 0.5).any()


def _confirmation() -> GeometryConfirmation:
    return GeometryConfirmation(FusionConfig(), Intrinsics.from_hfov(320, 240), Mount())


def _geometry_clear_everywhere(time_s: float) -> GeometryView:
    ones = np.ones(SHAPE, bool)
    return GeometryView(time_s, 0.5, ones, ~ones, np.full(SHAPE, 0.3, np.float32), np.full(SHAPE, 5.0, np.float32),
                        np.zeros(SHAPE), np.zeros(SHAPE, np.float32))


def test_ground_geometry_clears_after_the_camera_looked_past_it_is_confirmed_in_local_ned_only():
    confirm = _confirmation()
    confirm.view = _geometry_clear_everywhere(0.0)
    confirm.confirmed_view(_view(slice(20, 40)))         # the network saw rows 20-39 (landable)
    confirm.view = _geometry_clear_everywhere(5.0)       # geometry has cleared everything by now ...
    now = confirm.confirmed_view(_view(slice(0, 10)))    # ... and the camera sees rows 0-9 only
    assert now.landable[0:10].all() and now.landable[20:40].all()
    assert not now.landable[10:20].any()                  # never seen by the network: not confirmed
    assert now.clearance_m[30, 20] > 2.0                  # a whole disc there, out of the camera's view
    # A vehicle-centred grid's cells are not the same ground from frame to frame: only what it sees now.
    vehicle = _confirmation()
    vehicle.view = _geometry_clear_everywhere(0.0)
    vehicle.confirmed_view(_view(slice(20, 40), frame="vehicle"))
    vehicle.view = _geometry_clear_everywhere(5.0)
    only_now = vehicle.confirmed_view(_view(slice(0, 10), frame="vehicle"))
    assert only_now.landable[0:10].all() and not only_now.landable[10:].any()


def test_what_the_network_calls_vertical_at_its_last_look_is_never_confirmed_from_an_earlier_look():
    confirm = _confirmation()
    confirm.view = _geometry_clear_everywhere(0.0)
    confirm.confirmed_view(_view(slice(0, 40)))
    confirm.view = _geometry_clear_everywhere(1.0)
    # Seen again, not landable and HVO says 0 % horizontal: an objection.
    vertical = _view(slice(20, 40), landable_rows=slice(0, 0), horizontal=0.0)
    confirm.confirmed_view(vertical)
    confirm.view = _geometry_clear_everywhere(2.0)
    out = confirm.confirmed_view(_view(slice(0, 5)))
    assert out.landable[0:20].all() and not out.landable[20:40].any()


def test_the_evidence_says_when_the_network_no_longer_sees_the_spot():
    from edge_landing.runtime.fusion.landing import choose_spot

    confirm = _confirmation()
    confirm.view = _geometry_clear_everywhere(0.0)
    confirm.confirmed_view(_view(slice(20, 40)))
    confirm.view = _geometry_clear_everywhere(4.0)
    now_view = _view(slice(0, 2))                       # too few rows for a disc where the camera looks now
    confirmed = confirm.confirmed_view(now_view)
    choice = choose_spot(confirmed, (15.0, 10.0), FusionConfig(), None)
    assert choice is not None and choice.north_m >= 10.0
    assert confirm.verdict_note(choice, now_view) == "; out of the network's view now (its last look 4.0 s ago)"
    seen_now = _view(slice(0, 40))
    assert confirm.verdict_note(choice, seen_now) == ""


def test_a_remembered_cell_whose_sums_fusion_dropped_is_not_confirmed():
    confirm = _confirmation()
    confirm.view = _geometry_clear_everywhere(0.0)
    confirm.confirmed_view(_view(slice(20, 40)))
    confirm.view = _geometry_clear_everywhere(1.0)
    out = confirm.confirmed_view(_view(slice(0, 10), held_rows=slice(0, 30)))   # rows 30-39 left fusion's grid
    assert out.landable[20:30].all() and not out.landable[30:40].any()
