"""Thin obstacles and the flow's patch (ARCHITECTURE.md §11, MotionConfig.thin_obstacle_m): a pixel whose DIS patch
covers more ground than an obstacle is wide reads that obstacle at a fraction of its height, so it may confirm only
what an obstacle ``thin_obstacle_m`` / 1.2 across would have shown. On a generated flight: the disc beside a garden
wall that the stage used to confirm from 77 m is no longer confirmed, and the flight still gets targets."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from edge_landing.benchmarks.landing_truth import TruthConfig, check_target
from edge_landing.benchmarks.lying_model import lying_prediction
from edge_landing.runtime.core.camera import Mount
from edge_landing.runtime.core.messages import VehicleState
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser

sim = pytest.importorskip("edge_landing.sim", reason="the sim extra (embreex) renders the flight")


def test_the_lying_model_gets_no_target_beside_a_thin_wall_seen_from_77_m():
    """Suburban 3141 with hazards, the turning approach (``--approach arc``), 640×480, the lying model: the
    stage used to confirm a disc whose rim a 0.73 m tall, 0.24 m thick concrete wall crosses, from 77 m (a DIS
    patch covers 0.97 m there and read the wall at -0.01 to 0.15 m), and send it from frame 24 on. The first 32
    frames: every target lies on ground-truth safe ground, and there are some (frames 30-31 when written)."""
    from edge_landing.sim.generate import SimConfig, render_sample, vehicle_samples

    scfg = SimConfig(out=Path("."), frames=200, style=sim.Style.SUBURBAN, seed=3141, flight=True, fps=10.0,
                     width=640, height=480, approach=sim.Approach.ARC)
    world = sim.build_world(scfg.style, 3141, hazards=True)
    mount, intr = Mount(), scfg.intrinsics
    renderer = sim.Renderer(world, intr, mount)
    fusion = FusionConfig()
    fuser = LandingFuser(fusion, intr, mount)
    truth = TruthConfig(log="", clearance_m=fusion.required_clearance_m)
    wall_spot = np.array([214.25, -58.25])          # the disc confirmed before (its rim 1.8 m from the wall)
    targets = []
    for k, s in enumerate(vehicle_samples(scfg, world)):
        if k >= 32:
            break
        r = render_sample(scfg, k, s, renderer)
        state = VehicleState(s.t_s, s.attitude, s.position_ned_m.copy(), s.agl_m, "sim")
        target = fuser.update(lying_prediction(intr, mount, state, k), state, s.t_s, r.rgb)
        if target.valid:
            targets.append((k, check_target(world, *target.position_ned_m[:2], truth),
                            float(np.linalg.norm(target.position_ned_m[:2] - wall_spot))))
    assert targets, "no target at all: the check below would be vacuous"
    assert all(ok for _, (ok, _), _ in targets), targets
    assert min(d for _, _, d in targets) > 2.0, targets
    assert check_target(world, *wall_spot, truth) == (False, "height step 0.73 m inside the disc")
