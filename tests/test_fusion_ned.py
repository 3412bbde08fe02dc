"""Fusion's NED grid across frames (ARCHITECTURE.md §6 step 6) with network-like depth: per-frame scale errors.

The shipped model's depth scale wanders by ~1 % from frame to frame, i.e. 0.5-1 m of height at 40-80 m,
while a cell may spread 0.1 m. The NED grid therefore accumulates per-frame verdicts, never raw heights.
"""
from __future__ import annotations

import math

import numpy as np

from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount
from edge_landing.runtime.core.messages import Prediction
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
from tests.fusion_scenes import Box, Scene, gt_disc_ok, state_at

INTR = Intrinsics.from_hfov(160, 120)
MOUNT = Mount()
ALT_M = 40.0
# Single frames / analytic renders without camera images: motion geometry cannot confirm, so these
# network-evidence tests run with the explicit flag (ARCHITECTURE.md §11).
CFG = FusionConfig(allow_unconfirmed=True)
NEED_M = CFG.required_clearance_m
FPS = 10.0


def _dist_to_box_m(p, box: Box) -> float:
    return math.hypot(max(box.lo[0] - p[0], 0.0, p[0] - box.hi[0]), max(box.lo[1] - p[1], 0.0, p[1] - box.hi[1]))


def _scaled(render, frame_id: int, t_s: float, scale: float) -> Prediction:
    return Prediction(frame_id, t_s, (render.depth_m * np.float32(scale)).astype(np.float32), render.probs())


def test_ned_grid_keeps_finding_targets_under_per_frame_depth_scale_errors():
    boxes = (Box((8.0, -3.0, -10.0), (12.0, 3.0, 0.0)), Box((20.0, 4.0, -6.0), (26.0, 12.0, 0.0)))
    scene = Scene(boxes=boxes)
    fuser = LandingFuser(CFG, INTR, MOUNT)
    spreads = []
    for i in range(12):
        t_s = i / FPS
        pos = np.array([0.5 * t_s, 0.2 * t_s, -ALT_M])
        att = Attitude(0.01 * math.sin(i), 0.01 * math.cos(i), 0.1)
        render = scene.render(INTR, MOUNT, att, pos)
        scale = 1.0 + 0.015 * (-1) ** i                     # ±1.5 %: ~0.8 m of height between frames here
        target = fuser.update(_scaled(render, i, t_s, scale), state_at(t_s, pos, att), now_s=t_s)
        assert target.valid, (i, target.reason)
        n, e = target.position_ned_m[:2]
        for box in boxes:
            assert _dist_to_box_m((n, e), box) >= NEED_M - 1e-6, (i, box)
        ok, _, why = gt_disc_ok(render, (n, e, 0.0), NEED_M, 0.05)   # the true ground there is level, down = 0
        assert ok, (i, why)
        cell = fuser.grid.cell_of(n, e)
        spreads.append(float(fuser.grid.spread_m[cell]))
    # Not vacuous: mixing the frames' raw heights gives the chosen cells far more than the spread limit.
    assert max(spreads) > 5 * CFG.max_height_spread_m


def test_ned_grid_obstacle_outvotes_older_clear_views():
    """A pole appears on the chosen spot: within decay_s·ln(1/min_vote_share) the target leaves it."""
    fuser = LandingFuser(CFG, INTR, MOUNT)
    pos, att = np.array([0.0, 0.0, -ALT_M]), Attitude()
    flat = Scene().render(INTR, MOUNT, att, pos)
    i = 0
    for i in range(20):
        target = fuser.update(_scaled(flat, i, i / FPS, 1.0), state_at(i / FPS, pos, att), now_s=i / FPS)
        assert target.valid, target.reason
    n, e = target.position_ned_m[:2]
    pole = Box((n - 0.5, e - 0.5, -12.0), (n + 0.5, e + 0.5, 0.0))
    with_pole = Scene(boxes=(pole,)).render(INTR, MOUNT, att, pos)
    frames_needed = math.ceil(CFG.decay_s * math.log(1.0 / CFG.min_vote_share) * FPS) + 1
    for _k in range(1, frames_needed + 1):
        i += 1
        target = fuser.update(_scaled(with_pole, i, i / FPS, 1.0), state_at(i / FPS, pos, att), now_s=i / FPS)
    assert target.valid, target.reason
    assert _dist_to_box_m(target.position_ned_m[:2], pole) >= NEED_M - 1e-6
    cell = fuser.grid.cell_of(n, e)
    assert not fuser.grid.landable[cell]
