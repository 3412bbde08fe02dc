"""The ground-truth landing checker really tells safe from unsafe spots (sim world geometry)."""
import json

import numpy as np
import pytest

pytest.importorskip("embreex")

from edge_landing import sim  # noqa: E402
from edge_landing.benchmarks.landing_truth import TruthConfig, check_target, evaluate  # noqa: E402


@pytest.fixture(scope="module")
def world():
    return sim.build_world("suburban", 0)


def open_spot(world):
    """An open landing spot of the generator well inside the world's edge."""
    spots = world.landing_spots[np.abs(world.landing_spots).max(axis=1) < 400]
    return spots[0]


def test_open_ground_passes_and_a_pitched_roof_fails(world, tmp_path):
    cfg = TruthConfig(log="", clearance_m=2.0)
    n, e = open_spot(world)
    assert check_target(world, n, e, cfg) == (True, "ok")
    tilt = np.degrees(np.arccos(np.abs(world.normals[:, 2])))
    inside = np.abs(world.tris[:, :, :2]).max(axis=(1, 2)) < 400
    pitched = (world.material == sim.world.Material.ROOF_TILE) & (tilt > 20) & (tilt < 60) & inside
    roof = np.flatnonzero(pitched)[0]                                 # a pitched roof face of a house
    n, e = world.tris[roof].mean(axis=0)[:2]
    ok, why = check_target(world, n, e, cfg)
    assert not ok and ("tilted" in why or "step" in why)
    log = tmp_path / "t.jsonl"
    ln, le = open_spot(world)
    log.write_text("\n".join(json.dumps(r) for r in (
        {"frame": 0, "valid": True, "ned_m": [float(ln), float(le), 0.0]},
        {"frame": 1, "valid": True, "ned_m": [float(n), float(e), 0.0]},
        {"frame": 2, "valid": False, "ned_m": None})) + "\n")
    result = evaluate(TruthConfig(log=str(log)))
    assert (result["targets"], result["safe"]) == (2, 1) and result["failures"][0]["frame"] == 1
