"""A keyframe whose pair failed is scored by the noise it gave, for windows over the ground that pair looked at,
while other pairs hold (ARCHITECTURE.md §11): the ring's keyframe with the longest baseline is the best on paper,
but one taken above a tall building sees the ground behind the roof's edge, and a hover would pair every frame
with it; the same keyframe may pair well on other ground. When every pair fails (rain), no keyframe is blamed.
Renders are real sim worlds (Embree ray casting)."""
from __future__ import annotations

import math
from collections import deque
from dataclasses import replace
from typing import Deque

import cv2
import numpy as np
import pytest

from edge_landing.runtime.fusion.keyframes import Keyframe, PairNoise, WindowGround, pick_reference, window_ground
from edge_landing.runtime.fusion.motion import CameraPose, MotionConfig, MotionStage

sim = pytest.importorskip("edge_landing.sim", reason="the sim extra (embreex) renders the test worlds")
from tests.test_confirm_decisions import _stage_after_a_descent_along_the_line_of_sight  # noqa: E402
from tests.test_motion import INTR, MOUNT, _flat_world, _frames  # noqa: E402

CFG = MotionConfig()
HERE = WindowGround(np.array([40.0, 25.0]), 12.0)


def _pick(stage: MotionStage, pose: CameraPose, window, memory=None):
    return pick_reference(stage._history, pose, window, stage.k_cv, stage._k_inv, stage.size_hw, CFG, memory)


def test_a_failed_keyframe_is_scored_by_its_noise_while_other_pairs_hold():
    stage, pose = _stage_after_a_descent_along_the_line_of_sight(3.0, 8)     # baselines 3 ... 24 m, times < 0
    window = stage._window(pose, np.array([40.0, 25.0, 0.0]))
    assert window is not None
    best, det_best, _ = _pick(stage, pose, window)
    assert best is not None and math.isfinite(det_best)
    others = [kf.time_s for kf in stage._history if kf.time_s != best.time_s]
    ground = window_ground(pose, window, stage._k_inv)
    assert ground is not None
    noise = PairNoise()
    noise.remember(stage._history, others[0], -0.1, 0.3, ground, CFG)         # a pair that held, 0.1 s ago
    noise.remember(stage._history, best.time_s, 0.0, 4.0, ground, CFG)        # 20 × the 0.2 px floor: failed
    assert noise.penalised(0.0, ground, CFG) == {best.time_s: 4.0}
    other, _, _ = _pick(stage, pose, window, noise.penalised(0.0, ground, CFG))
    assert other is not None and other.time_s != best.time_s
    # Alone in the ring, the failed keyframe is still paired, its score scaled by its noise over the floor.
    alone = [kf for kf in stage._history if kf.time_s == best.time_s]
    stage._history.clear()
    stage._history.extend(alone)
    _, det_alone, _ = _pick(stage, pose, window, noise.penalised(0.0, ground, CFG))
    assert det_alone == pytest.approx(det_best * 4.0 / CFG.flow_noise_px)
    assert _pick(stage, pose, window, {best.time_s: 0.1})[1] == pytest.approx(det_best)   # never below the floor
    noise.remember(stage._history, best.time_s, 0.1, 0.3, ground, CFG)        # a pair with it held: forgotten
    assert noise.failed == {}


def test_no_keyframe_is_blamed_when_no_pair_held_within_the_history():
    stage, pose = _stage_after_a_descent_along_the_line_of_sight(3.0, 8)
    window = stage._window(pose, np.array([40.0, 25.0, 0.0]))
    best, det_best, _ = _pick(stage, pose, window)
    assert best is not None
    noise = PairNoise()
    for kf in stage._history:                                                 # rain: every pair failed
        noise.remember(stage._history, kf.time_s, 0.0, 3.0, HERE, CFG)
    assert len(noise.failed) == len(stage._history)
    assert noise.penalised(0.0, HERE, CFG) == {}
    kept, det, _ = _pick(stage, pose, window, noise.penalised(0.0, HERE, CFG))
    assert kept is best and det == pytest.approx(det_best)                   # the longest useful baseline stays
    noise.remember(stage._history, best.time_s, 1.0, 0.3, HERE, CFG)          # one held: the others are blamed
    assert len(noise.penalised(1.0, HERE, CFG)) == len(stage._history) - 1
    assert noise.penalised(1.0 + CFG.history_s + 0.1, HERE, CFG) == {}        # ... for history_s, no longer
    assert noise.penalised(0.5, HERE, CFG) == {}                              # (time went back: nothing)
    noise.clear()
    assert noise.failed == {} and noise.held_s == -math.inf


def test_the_memory_holds_only_failed_pairs_of_keyframes_still_in_the_ring():
    stage, _ = _stage_after_a_descent_along_the_line_of_sight(3.0, 4)
    times = [kf.time_s for kf in stage._history]
    noise = PairNoise()
    noise.failed[-99.0] = [(5.0, HERE)]                                       # a keyframe long gone
    noise.remember(stage._history, times[0], 0.0, CFG.max_plane_noise_px, HERE, CFG)   # at the limit: held
    assert noise.failed == {} and noise.held_s == 0.0
    noise.remember(stage._history, times[1], 0.1, 1.5, HERE, CFG)
    assert noise.failed == {times[1]: [(1.5, HERE)]} and noise.held_s == 0.0
    for k in range(2 * PairNoise.MAX_PER_KEYFRAME):                          # failures over ground far apart
        there = WindowGround(np.array([100.0 * (k + 1), 0.0]), 12.0)
        noise.remember(stage._history, times[1], 0.2 + k, 2.0 + k, there, CFG)
    assert len(noise.failed[times[1]]) == PairNoise.MAX_PER_KEYFRAME         # the newest are kept
    assert noise.failed[times[1]][-1][0] == 2.0 + 2 * PairNoise.MAX_PER_KEYFRAME - 1


def _swirled(grey: np.ndarray) -> np.ndarray:
    """The keyframe's image bent by a few pixels: its flow against any later frame fails across the epipolar
    lines, as ground seen past a roof's edge does."""
    yy, xx = np.mgrid[0:grey.shape[0], 0:grey.shape[1]].astype(np.float32)
    out: np.ndarray = cv2.remap(grey, xx + 3 * np.sin(yy / 7), yy + 3 * np.cos(xx / 9), cv2.INTER_LINEAR)
    return out


def test_a_hover_stops_pairing_with_the_keyframe_that_failed():
    world = _flat_world([[40.0, 0.0, 3.0, 3.0, 2.0]])
    path = [(-10.0 + 1.0 * k, 0.0, -35.0) for k in range(12)] + [(1.5, 0.0, -35.0)] * 3   # fly, then hover
    stage = MotionStage(CFG, INTR, MOUNT)
    results = []
    for k, t, r, state in _frames(world, path):
        pose = CameraPose.of(MOUNT, state.attitude, state.position_ned_m, state.agl_m)
        if k == 12:   # spoil the keyframe the first hover frame will pair with (the longest baseline)
            window = stage._window(pose, None)
            stage._scan = (stage._scan - 1) % 6
            ref, _ = stage._pick_reference(pose, window, t)
            assert ref is not None
            at = [kf.time_s for kf in stage._history].index(ref.time_s)
            stage._history[at] = replace(ref, grey=_swirled(ref.grey))
            spoiled = ref.time_s
        results.append(stage.update(r.rgb, pose, t))
    assert all(res is not None and res.flow_noise_px <= CFG.max_plane_noise_px for res in results[1:12])  # held
    first, *rest = results[12:]
    assert first is not None and first.flow_noise_px > CFG.max_plane_noise_px      # the spoiled pair failed
    assert max(n for n, _ in stage._pair_noise.failed.get(spoiled, [(0.0, None)])) > CFG.max_plane_noise_px
    assert spoiled in [kf.time_s for kf in stage._history]                          # still in the ring, but
    for res in rest:                                                                # the hover pairs elsewhere
        assert res is not None and res.reference_age_s != pytest.approx(res.time_s - spoiled)
        assert res.flow_noise_px <= CFG.max_plane_noise_px
    stage.reset()
    assert stage._pair_noise.failed == {} and stage._pair_noise.held_s == -math.inf


def _ring(times: list[float]) -> Deque[Keyframe]:
    """Keyframes at ``times`` (their images and poses play no part in the memory)."""
    pose = CameraPose(np.eye(3), np.zeros(3), 40.0)
    return deque(Keyframe(t, np.zeros((4, 4), np.uint8), pose) for t in times)


def test_a_failure_counts_only_for_windows_over_the_ground_it_looked_at():
    """Urban 5150 (docs/MEASUREMENTS.md): keyframes that failed in the approach, looking past a roof's edge 100 m
    away, gave perfect pairs over the hover's ground; blamed everywhere, they left the hover an 8 m baseline."""
    roof, field = WindowGround(np.array([-234.0, 134.0]), 24.0), WindowGround(np.array([-160.0, 62.0]), 18.0)
    noise = PairNoise()
    noise.remember(_ring([1.0, 2.0]), 1.0, 5.0, 3.6, roof, CFG)            # failed past the roof's edge
    noise.remember(_ring([1.0, 2.0]), 2.0, 5.2, 0.2, roof, CFG)            # another keyframe held there
    assert noise.penalised(5.4, roof, CFG) == {1.0: 3.6}
    near = WindowGround(roof.centre_ne_m + [20.0, 0.0], 5.0)                  # inside the failed footprint
    assert noise.penalised(5.4, near, CFG) == {1.0: 3.6}
    assert noise.penalised(5.4, field, CFG) == {}                             # other ground: not blamed
    assert noise.penalised(5.4, None, CFG) == {1.0: 3.6}                      # no ground known: blamed
    noise.remember(_ring([1.0, 2.0]), 1.0, 5.6, 0.2, field, CFG)           # held over the field ...
    assert noise.penalised(5.8, roof, CFG) == {1.0: 3.6}                      # ... the roof's failure stays
    noise.remember(_ring([1.0, 2.0]), 1.0, 5.8, 0.2, near, CFG)            # held over that ground: taken back
    assert noise.failed == {}


def test_a_window_s_ground_is_where_its_rays_meet_the_plane():
    stage, pose = _stage_after_a_descent_along_the_line_of_sight(3.0, 4)
    window = stage._window(pose, np.array([40.0, 25.0, 0.0]))
    assert window is not None
    ground = window_ground(pose, window, stage._k_inv)
    assert ground is not None
    rs, cs = window
    ray = pose.r_nc @ stage._k_inv @ np.array([0.5 * (cs.start + cs.stop), 0.5 * (rs.start + rs.stop), 1.0])
    hit = pose.position_ned_m + ray * pose.agl_m / ray[2]
    assert np.allclose(ground.centre_ne_m, hit[:2])
    assert np.hypot(*(ground.centre_ne_m - [40.0, 25.0])) < ground.radius_m   # the spot it was centred on
    assert 1.0 < ground.radius_m < 60.0
    up = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])       # camera z to NED up
    assert window_ground(CameraPose(up, pose.position_ned_m, pose.agl_m), window, stage._k_inv) is None
