"""Where the time goes: ONNX Runtime's own profiler, summed per operator type.

    ops = profile_ops("m.int8.onnx", contract, threads=2, runs=10)
    for op in ops[:5]:
        print(op.op_type, op.total_ms, op.share)
"""
from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import List

from edge_landing.runtime.perception.contract import ModelContract

from .speed import input_tensor


@dataclass(frozen=True)
class OpTime:
    op_type: str
    total_ms: float      # per inference, summed over all nodes of this type
    share: float         # of the summed kernel time
    nodes: int

    def to_json(self) -> dict:
        return {"op_type": self.op_type, "ms_per_run": self.total_ms, "share": self.share, "nodes": self.nodes}


def profile_ops(path: os.PathLike | str, contract: ModelContract, threads: int = 2, runs: int = 10,
                warmup: int = 2) -> List[OpTime]:
    """Kernel time per operator type (after ONNX Runtime's graph optimisations and fusions), largest first."""
    import onnxruntime as ort

    with tempfile.TemporaryDirectory(prefix="edge-profile-") as tmp:
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.log_severity_level = 3
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        sess = ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
        feed = {contract.input.name: input_tensor(contract)}
        for _ in range(warmup):
            sess.run(None, feed)
        opts_prof = ort.SessionOptions()
        opts_prof.intra_op_num_threads = threads
        opts_prof.inter_op_num_threads = 1
        opts_prof.log_severity_level = 3
        opts_prof.enable_profiling = True
        opts_prof.profile_file_prefix = str(Path(tmp) / "ort")
        sess = ort.InferenceSession(str(path), sess_options=opts_prof, providers=["CPUExecutionProvider"])
        for _ in range(warmup + runs):
            sess.run(None, feed)
        trace = Path(sess.end_profiling())
        events = json.loads(trace.read_text())
    return summarise(events, runs_after_warmup=runs, warmup=warmup)


def summarise(events: list, runs_after_warmup: int, warmup: int) -> List[OpTime]:
    """Sum 'Node' kernel events per op type over the runs after warm-up (the trace holds every run)."""
    runs_seen = -1
    per_op: dict[str, float] = {}
    nodes: dict[str, set[str]] = {}
    for ev in events:
        if ev.get("cat") == "Session" and ev.get("name") == "model_run":
            runs_seen += 1
        if ev.get("cat") != "Node" or not str(ev.get("name", "")).endswith("_kernel_time"):
            continue
        op = ev.get("args", {}).get("op_name", "?")
        nodes.setdefault(op, set()).add(ev["name"])
        # model_run events close after their nodes, so a node belongs to run number runs_seen + 1
        if runs_seen + 1 >= warmup:
            per_op[op] = per_op.get(op, 0.0) + ev.get("dur", 0) / 1e3
    total = sum(per_op.values()) or 1.0
    out = [OpTime(op, ms / max(runs_after_warmup, 1), ms / total, len(nodes[op])) for op, ms in per_op.items()]
    return sorted(out, key=lambda o: o.total_ms, reverse=True)
