"""Continuity without a telemetry position (ARCHITECTURE.md §12): the committed spot is kept in the frame the
images placed the vehicle in (fusion.result.ImagePlacement), held targets leave as body vectors only, and the
spot goes when that frame changes or a frame cannot be placed."""
from __future__ import annotations

import math

import numpy as np

from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount
from edge_landing.runtime.core.messages import EVIDENCE_GEOMETRY, Prediction, Target, VehicleState
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
from edge_landing.runtime.fusion.result import ImagePlacement
from edge_landing.runtime.pipeline.trust import HELD, Continuity, ContinuityConfig
from tests.run_helpers import ground_plane_depth

AGL_M = 10.0
YAW_RAD = math.radians(30.0)


def _state(t: float) -> VehicleState:
    """Attitude and height above ground, no position (a drone without GPS)."""
    return VehicleState(t, Attitude(0.0, 0.0, YAW_RAD), None, AGL_M, "rangefinder")


def _target(frame: int, spot_ned_m: np.ndarray, at: ImagePlacement) -> Target:
    """A geometry-confirmed target at ``spot_ned_m`` (the odometry's frame) seen from ``at``: body FRD only."""
    body = Attitude(0.0, 0.0, YAW_RAD).ned_from_body().T @ (spot_ned_m - at.position_ned_m)
    return Target(frame, 0.1 * frame, True, position_body_frd_m=body, clearance_m=3.0, confidence=0.9,
                  evidence=EVIDENCE_GEOMETRY)


def _committed(spot: np.ndarray, place) -> Continuity:
    cont = Continuity(ContinuityConfig())
    for i in range(3):
        out, said = cont.step(_target(i, spot, place(i)), _state(0.1 * i), None, True, place(i))
        assert out.valid and said == ""
    assert cont.spot is not None
    np.testing.assert_allclose(cont.spot.ned_m, spot, atol=1e-9)
    return cont


def _placed(i: int, epoch: int = 2) -> ImagePlacement:
    return ImagePlacement(np.array([100.0 + 0.5 * i, 50.0, -AGL_M]), epoch)


def test_a_spot_without_telemetry_position_is_held_in_the_images_frame():
    """Committed from three placed frames, then re-sent while fusion gives nothing: the body vector follows the
    vehicle's placed motion; no local NED leaves (PX4 would read the odometry's frame as its own)."""
    spot = np.array([108.0, 52.0, 0.0])
    cont = _committed(spot, _placed)
    assert not cont.in_telemetry_frame()
    for i in range(4, 9):
        out, said = cont.step(Target.none(i, 0.1 * i, "no safe spot"), _state(0.1 * i), None, True, _placed(i))
        assert out.valid and out.reason.startswith(HELD) and said == ""
        assert out.position_ned_m is None
        want = Attitude(0.0, 0.0, YAW_RAD).ned_from_body().T @ (spot - _placed(i).position_ned_m)
        np.testing.assert_allclose(out.position_body_frd_m, want, atol=1e-9)
        assert out.range_m == float(np.linalg.norm(want))


def test_a_target_elsewhere_sends_the_committed_spot_and_a_far_one_is_not_taken():
    """The same rules as with a telemetry position: a target 10 m off sends the spot instead; a first spot
    farther than twice the height is held back."""
    spot = np.array([108.0, 52.0, 0.0])
    cont = _committed(spot, _placed)
    out, _ = cont.step(_target(4, spot + [10.0, 0.0, 0.0], _placed(4)), _state(0.4), None, True, _placed(4))
    assert out.valid and "chose a spot 10.0 m away" in out.reason and out.position_ned_m is None
    fresh = Continuity(ContinuityConfig())
    far = _placed(0).position_ned_m + np.array([30.0, 0.0, AGL_M])
    out, _ = fresh.step(_target(0, far, _placed(0)), _state(0.0), None, True, _placed(0))
    assert not out.valid and "beyond the 2:1 cone" in out.reason


def test_the_spot_goes_when_the_odometry_starts_over_or_a_frame_is_not_placed():
    spot = np.array([108.0, 52.0, 0.0])
    cont = _committed(spot, _placed)
    out, said = cont.step(Target.none(4, 0.4, "no safe spot"), _state(0.4), None, True, _placed(4, epoch=3))
    assert not out.valid and said == "spot dropped: image odometry started over" and cont.spot is None
    cont = _committed(spot, _placed)
    out, said = cont.step(Target.none(4, 0.4, "no safe spot"), _state(0.4), None, True, None)
    assert not out.valid and said.startswith("spot dropped: its frame changed") and cont.spot is None
    # Chained through a short gap from the last telemetry position (odometry_epoch None), then the position is
    # back: dropped, as the position after a gap may have drifted without a jump to say so.
    cont = _committed(spot, lambda i: _placed(i, epoch=None))
    assert not cont.in_telemetry_frame()
    with_position = VehicleState(0.4, Attitude(0.0, 0.0, YAW_RAD), _placed(4).position_ned_m, AGL_M, "sim")
    out, said = cont.step(Target.none(4, 0.4, "no safe spot"), with_position, None, True)
    assert not out.valid and said.startswith("spot dropped: its frame changed") and cont.spot is None


def test_fresh_evidence_on_the_vehicle_centred_grid_contradicts_a_placed_spot():
    """Without a position fusion's grid is around the vehicle; moved to the placed frame, the cells seen at the
    spot and judged not landable drop it at once (the whole disc in view), as in the telemetry's frame."""
    fuser = LandingFuser(FusionConfig(), Intrinsics.from_hfov(64, 48, math.radians(90.0)),
                         Mount(pitch_rad=math.radians(-45.0)))
    state = _state(0.4)
    depth = ground_plane_depth(48, 64, AGL_M, fuser.mount)
    hvo = np.zeros(depth.shape + (3,), np.float32)
    hvo[..., 0] = 1.0
    grid = fuser.fuse(Prediction(4, 0.4, depth, hvo), state, 0.4).grid
    assert grid is not None and grid.frame == "vehicle"
    ahead = Attitude(0.0, 0.0, YAW_RAD).ned_from_body() @ np.array([8.0, 0.0, AGL_M])   # 8 m ahead, on the ground
    cell = grid.cell_of(float(ahead[0]), float(ahead[1]))
    assert cell is not None and grid.landable[cell] and grid.seen[cell] == 1.0
    place = _placed(3)
    spot = place.position_ned_m + ahead
    cont = _committed(spot, lambda i: place)
    kept, said = cont.step(Target.none(4, 0.4, "no safe spot"), state, grid, True, place)
    assert kept.valid and said == ""                                # all landable: no contradiction
    blocked = type(grid)(grid.frame, grid.cell_m, grid.north0_m, grid.east0_m, grid.ref_down_m, grid.sums,
                         np.zeros_like(grid.landable), np.zeros_like(grid.clearance_m), grid.votes, grid.seen,
                         grid.min_seen_weight)
    out, said = cont.step(Target.none(5, 0.5, "no safe spot"), state, blocked, True, place)
    assert not out.valid and said == "spot dropped: fresh evidence contradicts it" and cont.spot is None

