"""A keyframe whose pair failed is scored by the noise it gave, while other pairs hold (ARCHITECTURE.md §11): the
ring's keyframe with the longest baseline is the best on paper, but one taken above a tall building sees the ground
behind the roof's edge, and a hover would pair every frame with it. When every pair fails (rain), no keyframe is
blamed. Renders are real sim worlds (Embree ray casting)."""
from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from edge_landing.runtime.fusion.keyframes import PairNoise, pick_reference
from edge_landing.runtime.fusion.motion import CameraPose, MotionConfig, MotionStage

sim = pytest.importorskip("edge_landing.sim", reason="the sim extra (embreex) renders the test worlds")
from tests.test_confirm_decisions import _stage_after_a_descent_along_the_line_of_sight  # noqa: E402
from tests.test_motion import INTR, MOUNT, _flat_world, _frames  # noqa: E402

CFG = MotionConfig()


def _pick(stage: MotionStage, pose: CameraPose, window, memory=None):
    return pick_reference(stage._history, pose, window, stage.k_cv, stage._k_inv, stage.size_hw, CFG, memory)


def test_a_failed_keyframe_is_scored_by_its_noise_while_other_pairs_hold():
    stage, pose = _stage_after_a_descent_along_the_line_of_sight(3.0, 8)     # baselines 3 ... 24 m, times < 0
    window = stage._window(pose, np.array([40.0, 25.0, 0.0]))
    assert window is not None
    best, det_best, _ = _pick(stage, pose, window)
    assert best is not None and math.isfinite(det_best)
    others = [kf.time_s for kf in stage._history if kf.time_s != best.time_s]
    noise = PairNoise()
    noise.remember(stage._history, others[0], -0.1, 0.3, CFG)                 # a pair that held, 0.1 s ago
    noise.remember(stage._history, best.time_s, 0.0, 4.0, CFG)                # 20 × the 0.2 px floor: failed
    assert noise.penalised(0.0, CFG) == {best.time_s: 4.0}
    other, _, _ = _pick(stage, pose, window, noise.penalised(0.0, CFG))
    assert other is not None and other.time_s != best.time_s
    # Alone in the ring, the failed keyframe is still paired, its score scaled by its noise over the floor.
    alone = [kf for kf in stage._history if kf.time_s == best.time_s]
    stage._history.clear()
    stage._history.extend(alone)
    _, det_alone, _ = _pick(stage, pose, window, noise.penalised(0.0, CFG))
    assert det_alone == pytest.approx(det_best * 4.0 / CFG.flow_noise_px)
    assert _pick(stage, pose, window, {best.time_s: 0.1})[1] == pytest.approx(det_best)   # never below the floor
    noise.remember(stage._history, best.time_s, 0.1, 0.3, CFG)                # a pair with it held: forgotten
    assert noise.failed == {}


def test_no_keyframe_is_blamed_when_no_pair_held_within_the_history():
    stage, pose = _stage_after_a_descent_along_the_line_of_sight(3.0, 8)
    window = stage._window(pose, np.array([40.0, 25.0, 0.0]))
    best, det_best, _ = _pick(stage, pose, window)
    assert best is not None
    noise = PairNoise()
    for kf in stage._history:                                                 # rain: every pair failed
        noise.remember(stage._history, kf.time_s, 0.0, 3.0, CFG)
    assert len(noise.failed) == len(stage._history)
    assert noise.penalised(0.0, CFG) == {}
    kept, det, _ = _pick(stage, pose, window, noise.penalised(0.0, CFG))
    assert kept is best and det == pytest.approx(det_best)                   # the longest useful baseline stays
    noise.remember(stage._history, best.time_s, 1.0, 0.3, CFG)                # one held: the others are blamed
    assert len(noise.penalised(1.0, CFG)) == len(stage._history) - 1
    assert noise.penalised(1.0 + CFG.history_s + 0.1, CFG) == {}              # ... for history_s, no longer
    assert noise.penalised(0.5, CFG) == {}                                    # (time went back: nothing)
    noise.clear()
    assert noise.failed == {} and noise.held_s == -math.inf


def test_the_memory_holds_only_failed_pairs_of_keyframes_still_in_the_ring():
    stage, _ = _stage_after_a_descent_along_the_line_of_sight(3.0, 4)
    times = [kf.time_s for kf in stage._history]
    noise = PairNoise()
    noise.failed[-99.0] = 5.0                                                 # a keyframe long gone
    noise.remember(stage._history, times[0], 0.0, CFG.max_plane_noise_px, CFG)   # at the limit: held
    assert noise.failed == {} and noise.held_s == 0.0
    noise.remember(stage._history, times[1], 0.1, 1.5, CFG)
    assert noise.failed == {times[1]: 1.5} and noise.held_s == 0.0


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
    assert stage._pair_noise.failed.get(spoiled, 0.0) > CFG.max_plane_noise_px
    assert spoiled in [kf.time_s for kf in stage._history]                          # still in the ring, but
    for res in rest:                                                                # the hover pairs elsewhere
        assert res is not None and res.reference_age_s != pytest.approx(res.time_s - spoiled)
        assert res.flow_noise_px <= CFG.max_plane_noise_px
    stage.reset()
    assert stage._pair_noise.failed == {} and stage._pair_noise.held_s == -math.inf
