"""A keyframe whose pair failed is scored by the noise it gave (ARCHITECTURE.md §11): the ring's keyframe with the
longest baseline is the best on paper, but one taken above a tall building sees the ground behind the roof's edge,
and a hover would pair every frame with it. Renders are real sim worlds (Embree ray casting)."""
from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from edge_landing.runtime.fusion.keyframes import pick_reference, remember_pair_noise
from edge_landing.runtime.fusion.motion import CameraPose, MotionConfig, MotionStage

sim = pytest.importorskip("edge_landing.sim", reason="the sim extra (embreex) renders the test worlds")
from tests.test_confirm_decisions import _stage_after_a_descent_along_the_line_of_sight  # noqa: E402
from tests.test_motion import INTR, MOUNT, _flat_world, _frames  # noqa: E402

CFG = MotionConfig()


def _pick(stage: MotionStage, pose: CameraPose, window, memory=None):
    return pick_reference(stage._history, pose, window, stage.k_cv, stage._k_inv, stage.size_hw, CFG, memory)


def test_a_failed_keyframe_is_scored_by_its_noise_and_a_pair_that_held_clears_it():
    stage, pose = _stage_after_a_descent_along_the_line_of_sight(3.0, 8)     # baselines 3 ... 24 m
    window = stage._window(pose, np.array([40.0, 25.0, 0.0]))
    assert window is not None
    best, det_best, _ = _pick(stage, pose, window)
    assert best is not None and math.isfinite(det_best)
    memory: dict[float, float] = {}
    remember_pair_noise(memory, stage._history, best.time_s, 4.0, CFG)        # 20 × the 0.2 px floor
    other, det_other, _ = _pick(stage, pose, window, memory)
    assert other is not None and other.time_s != best.time_s
    # Alone in the ring, the failed keyframe is still paired, its score scaled by its noise over the floor.
    alone = [kf for kf in stage._history if kf.time_s == best.time_s]
    stage._history.clear()
    stage._history.extend(alone)
    _, det_alone, _ = _pick(stage, pose, window, memory)
    assert det_alone == pytest.approx(det_best * 4.0 / CFG.flow_noise_px)
    remember_pair_noise(memory, stage._history, best.time_s, 0.3, CFG)        # a pair that held: forgotten
    assert memory == {}
    assert _pick(stage, pose, window, {best.time_s: 0.1})[1] == pytest.approx(det_best)   # never below the floor


def test_the_memory_holds_only_failed_pairs_of_keyframes_still_in_the_ring():
    stage, _ = _stage_after_a_descent_along_the_line_of_sight(3.0, 4)
    times = [kf.time_s for kf in stage._history]
    memory = {-99.0: 5.0}                                                      # a keyframe long gone
    remember_pair_noise(memory, stage._history, times[0], CFG.max_plane_noise_px, CFG)   # at the limit: held
    assert memory == {}
    remember_pair_noise(memory, stage._history, times[1], 1.5, CFG)
    assert memory == {times[1]: 1.5}


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
            ref, _ = stage._pick_reference(pose, window)
            assert ref is not None
            at = [kf.time_s for kf in stage._history].index(ref.time_s)
            stage._history[at] = replace(ref, grey=_swirled(ref.grey))
            spoiled = ref.time_s
        results.append(stage.update(r.rgb, pose, t))
    first, *rest = results[12:]
    assert first is not None and first.flow_noise_px > CFG.max_plane_noise_px      # the spoiled pair failed
    assert stage._failed_noise_px.get(spoiled, 0.0) > CFG.max_plane_noise_px
    assert spoiled in [kf.time_s for kf in stage._history]                          # still in the ring, but
    for res in rest:                                                                # the hover pairs elsewhere
        assert res is not None and res.reference_age_s != pytest.approx(res.time_s - spoiled)
        assert res.flow_noise_px <= CFG.max_plane_noise_px
    stage.reset()
    assert stage._failed_noise_px == {}
