"""The lying-model replay's per-frame trace (benchmarks.lying_model --trace) agrees with its own counts."""
from __future__ import annotations

import json

import pytest

pytest.importorskip("edge_landing.sim", reason="the sim extra (embreex) renders the replayed flight")
from edge_landing.benchmarks.lying_model import ReplayConfig, replay  # noqa: E402


def test_trace_says_per_frame_what_was_sent_and_what_the_network_alone_had(tmp_path):
    trace = tmp_path / "trace.jsonl"
    result = replay(ReplayConfig(style="suburban", seed=5150, frames=12, width=320, height=240, trace=str(trace)))
    rows = [json.loads(line) for line in trace.read_text().splitlines()]
    assert [r["frame"] for r in rows] == list(range(12))
    stats = result["stats"]["lying"]
    assert sum(r["valid"] for r in rows) == stats["geometry"]["targets"]
    assert sum(r["sent"] for r in rows) == stats["sent"]["targets"]
    assert sum(r["network"] for r in rows) == stats["network"]["targets"] == 12   # the lying network always has one
