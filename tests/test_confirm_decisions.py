"""Which ground motion geometry measures and what may be confirmed (ARCHITECTURE.md §11): the keyframe's
baseline, the window among the network's candidate spots, and the network's veto by its HVO class.
Renders are real sim worlds (Embree ray casting)."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
from edge_landing.runtime.fusion.keyframes import Keyframe
from edge_landing.runtime.fusion.motion import CameraPose, MotionConfig, MotionStage

sim = pytest.importorskip("edge_landing.sim", reason="the sim extra (embreex) renders the test worlds")
from edge_landing.benchmarks.landing_truth import TruthConfig, check_target  # noqa: E402
from edge_landing.benchmarks.lying_model import lying_prediction  # noqa: E402
from tests.test_motion import _flat_world, _frames  # noqa: E402

INTR = Intrinsics.from_hfov(320, 240)
MOUNT = Mount()


def _stage_after_a_descent_along_the_line_of_sight(spacing_m: float, count: int) -> tuple[MotionStage, CameraPose]:
    """Keyframes flown down the camera's 45° line of sight towards the ground point A = (40, 0, 0)."""
    stage = MotionStage(MotionConfig(), Intrinsics.from_hfov(640, 480), MOUNT)   # the window: a quarter
    grey = np.zeros(stage.size_hw, np.uint8)
    here = np.array([0.0, 0.0, -40.0])
    back = np.array([-1.0, 0.0, -1.0]) / math.sqrt(2.0)
    for k in range(count, 0, -1):
        p = here + back * spacing_m * k
        stage._history.append(Keyframe(-0.2 * k, grey, CameraPose.of(MOUNT, Attitude(), p, float(-p[2]))))
    return stage, CameraPose.of(MOUNT, Attitude(), here, 40.0)


def test_the_window_goes_where_a_keyframe_sees_parallax_and_long_baselines_are_not_paired():
    stage, pose = _stage_after_a_descent_along_the_line_of_sight(6.0, 8)   # baselines 6 ... 48 m
    spot_a = np.array([40.0, 0.0, 0.0])       # where the vehicle flies to: the epipole, no parallax
    spot_b = np.array([40.0, 25.0, 0.0])      # landable ground off the line of flight
    window, ref = stage._choose_window(pose, np.stack([spot_a, spot_b]), 0.0)
    assert window is not None and ref is not None
    cam = pose.r_nc.T @ (spot_b - pose.position_ned_m)
    u = stage.k_cv[0, 0] * cam[0] / cam[2] + stage.k_cv[0, 2]
    assert window[1].start <= u < window[1].stop, (window, u)          # centred on B, not on A
    only_a, _ = stage._choose_window(pose, spot_a[None], 0.0)
    assert only_a is not None and only_a != window                     # not vacuous: A's window is elsewhere
    # The range to the window's ground is about 57-70 m: a keyframe 48 m back (ratio > 0.5) is never paired.
    baseline = float(np.linalg.norm(ref.pose.position_ned_m - pose.position_ned_m))
    assert baseline <= MotionConfig().max_baseline_ratio * 75.0
    far_only, _ = _stage_after_a_descent_along_the_line_of_sight(48.0, 1)
    _, none = far_only._pick_reference(pose, window, 0.0)
    assert none == math.inf and "usable baseline" in far_only.last_reason


def _noisy_depth(pred, rng, vertical: bool = False):
    """The liar's flat ground with 3 % depth noise (the network's height spread fails everywhere), HVO
    horizontal (or vertical) everywhere."""
    depth = pred.depth_m * (1.0 + 0.03 * rng.standard_normal(pred.depth_m.shape)).astype(np.float32)
    hvo = np.zeros_like(pred.hvo_prob)
    hvo[..., 1 if vertical else 0] = 1.0
    return replace(pred, depth_m=depth, hvo_prob=hvo)


def test_geometry_confirms_ground_the_network_calls_horizontal_but_not_flat_and_never_what_it_calls_vertical():
    cars = [[n, e, 2.2, 0.9, 1.5] for n in np.arange(15.0, 45.0, 5.0) for e in (-12.0, -6.0, 0.0, 6.0)]
    world = _flat_world(cars)
    path = [(-14.0 + 0.3 * k, -3.0 + 2.0 * math.sin(0.2 * k), -25.0) for k in range(50)]
    truth = TruthConfig(log="", clearance_m=FusionConfig().required_clearance_m)
    fusers = {"horizontal": LandingFuser(FusionConfig(), INTR, MOUNT),
              "strict": LandingFuser(FusionConfig(confirm_on_horizontal=False), INTR, MOUNT),
              "vertical": LandingFuser(FusionConfig(), INTR, MOUNT)}
    rng = np.random.default_rng(3)
    valid = {name: 0 for name in fusers}
    for k, t, r, state in _frames(world, path):
        pred = lying_prediction(INTR, MOUNT, state, k)
        for name, fuser in fusers.items():
            target = fuser.update(_noisy_depth(pred, rng, vertical=name == "vertical"), state, t, r.rgb)
            if target.valid:
                valid[name] += 1
                assert check_target(world, *target.position_ned_m[:2], truth)[0], (name, k)
            if name == "strict":
                assert not fuser.grid.landable.any() or not target.valid
    assert valid["horizontal"] > 10, valid     # geometry measured the grass: the network's noise does not veto it
    assert valid["strict"] == 0 and valid["vertical"] == 0, valid


def test_focus_candidates_take_the_best_spots_that_are_far_enough_apart():
    from edge_landing.runtime.fusion.focus import focus_candidates
    from edge_landing.runtime.fusion.grid import GridView

    config = FusionConfig()
    ok = config.required_clearance_m + 0.5
    clearance = np.zeros((40, 40), np.float32)
    for (row, col), extra in {(5, 5): 2.0, (7, 5): 2.0, (30, 5): 0.0, (5, 30): 0.5}.items():
        clearance[row, col] = ok + extra
    sums = np.zeros((5, 40, 40))
    sums[0], sums[1] = 1.0, 2.0                     # every cell observed once, 2 m down
    view = GridView("ned", 1.0, 0.0, 0.0, 0.0, sums, clearance > 0, clearance)
    first = np.array([39.5, 39.5, 1.0])              # the network's own spot comes first, whatever its score
    picks = focus_candidates(view, first, (0.0, 0.0), config)
    # (5, 5) scores best; (7, 5) is within 10 m of it; (5, 30) beats (30, 5) on clearance and travel alike.
    np.testing.assert_allclose(picks, [first, [5.5, 5.5, 2.0], [5.5, 30.5, 2.0]])
    np.testing.assert_allclose(focus_candidates(view, first, (0.0, 0.0), config, count=2), picks[:2])
    near_first = focus_candidates(view, np.array([6.0, 6.0, 1.0]), (0.0, 0.0), config, separation_m=40.0)
    np.testing.assert_allclose(near_first, [[6.0, 6.0, 1.0]])   # everything lies within 40 m of the first


def test_a_confirmed_spot_lies_at_the_level_geometry_measured_when_the_networks_depth_is_far_off():
    """The network's depth 60 % too long (a grazing view, a scale gone wrong) puts the ground 15 m below where it
    is. Geometry measured that ground: the target's level is geometry's, so its direction points at the real
    ground (an autopilot that takes only the direction, ArduPilot, would otherwise land metres short of the spot)."""
    world = _flat_world([[200.0, 200.0, 1.0, 1.0, 1.0]])       # (one box, far out of view: the helper needs one)
    path = [(-14.0 + 0.3 * k, -3.0 + 2.0 * math.sin(0.2 * k), -25.0) for k in range(50)]
    fusers = {"guarded": LandingFuser(FusionConfig(), INTR, MOUNT),
              "off": LandingFuser(FusionConfig(max_level_disagreement_m=math.inf), INTR, MOUNT)}
    downs: dict = {name: [] for name in fusers}
    for k, t, r, state in _frames(world, path):
        pred = lying_prediction(INTR, MOUNT, state, k)
        pred = replace(pred, depth_m=pred.depth_m * 1.6)
        for name, fuser in fusers.items():
            target = fuser.update(pred, state, t, r.rgb)
            if target.valid:
                downs[name].append((float(target.position_ned_m[2]), target.evidence))
    assert len(downs["guarded"]) >= 5 and len(downs["off"]) >= 5
    assert all(abs(d) < 0.5 and "level from geometry" in e for d, e in downs["guarded"]), downs["guarded"][:3]
    assert all(d > 10.0 for d, _ in downs["off"])               # the network's own level: 15 m under the field
