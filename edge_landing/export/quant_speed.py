"""edge-quantize's speed search: keep in float the branches that run slower in INT8 on this CPU (§9).

Without an int8 dot-product instruction (AVX2 + FMA only) ONNX Runtime's int8 convolutions widen to int16,
and the Q/DQ at every float/int8 border costs a pass over the tensor, so some parts of a net are faster in
float. Kernel times per node cannot be compared between the two files (ONNX Runtime renames and fuses
nodes differently in each), so the search measures the whole model: it takes the graph's top-level
branches (the first component of the exporter's node names, e.g. ``/enc2/...``, ``/hvo_head/...``), and
for each one in turn quantizes the net again with that branch left in float, times it against the best so
far (interleaved, same session settings as edge-run) and keeps the branch in float if that is faster by
more than ``margin``. Greedy and bounded: one quantization and one short timing per branch. Example::

    best, kept, record = search_float_branches(src, pre, first, excluded, build, config)
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Tuple

from edge_landing.runtime.core.choices import ChoiceEnum
from edge_landing.runtime.perception.precision import ProbeConfig, probe

log = logging.getLogger(__name__)

_COMPUTE_OPS = ("Conv", "ConvTranspose", "Gemm", "MatMul")


class SpeedSearch(ChoiceEnum):
    AUTO = "auto"        # search only when full INT8 is less than SearchConfig.below x FP32 here
    ALWAYS = "always"
    NEVER = "never"

    @classmethod
    def _label(cls) -> str:
        return "--speed-search"


@dataclass(frozen=True)
class SearchConfig:
    mode: SpeedSearch = SpeedSearch.AUTO
    below: float = 1.3       # AUTO searches when INT8/FP32 images/s is under this (the goal for EdgeNet)
    margin: float = 0.03     # a branch stays float only if that is >3 % faster (timing noise on a shared CPU)
    threads: int = 2
    iterations: int = 20


def branch_groups(model, excluded: List[str]) -> Dict[str, List[str]]:
    """Top-level branch -> its node names, for branches with a compute op not already kept float."""
    groups: Dict[str, List[str]] = {}
    has_compute: Dict[str, bool] = {}
    skip = set(excluded)
    for node in model.graph.node:
        parts = node.name.split("/")
        if not node.name.startswith("/") or len(parts) < 3 or node.name in skip:
            continue
        groups.setdefault(parts[1], []).append(node.name)
        has_compute[parts[1]] = has_compute.get(parts[1], False) or node.op_type in _COMPUTE_OPS
    return {g: names for g, names in groups.items() if has_compute[g]}


def search_float_branches(src: Path, pre: Path, first: Path, excluded: List[str],
                          build: Callable[[List[str], Path], object], config: SearchConfig
                          ) -> Tuple[Path, List[str], dict]:
    """(best INT8 file, extra node names kept float, record for edge.quantization).

    ``first`` is the INT8 file quantized with ``excluded`` only; ``build(extra, path)`` quantizes again with
    ``excluded + extra`` in float and writes ``path`` (with the contract, so that it loads like any model).
    """
    import onnx

    probe_cfg = ProbeConfig(threads=config.threads, warmup=3, iterations=config.iterations, max_seconds=30.0)
    fp32_s, int8_s = probe(src, first, probe_cfg)
    record: dict = {"mode": config.mode.value, "int8_vs_fp32_full": fp32_s / int8_s}
    if config.mode is SpeedSearch.NEVER or (config.mode is SpeedSearch.AUTO and fp32_s / int8_s >= config.below):
        record["ran"] = False
        return first, [], record
    groups = branch_groups(onnx.load(str(pre)), excluded)
    best, kept, steps = first, [], []
    kept_names: List[str] = []
    for i, (branch, names) in enumerate(groups.items()):
        candidate = first.with_name(f"search_{i}.onnx")
        build(kept_names + names, candidate)
        before_s, cand_s = probe(best, candidate, probe_cfg)
        keep = cand_s < before_s * (1.0 - config.margin)
        steps.append({"branch": branch, "nodes": len(names), "int8_p50_ms": before_s * 1e3,
                      "with_branch_float_p50_ms": cand_s * 1e3, "kept_float": keep})
        log.info("speed search: %s float %.2f ms vs %.2f ms -> %s", branch, cand_s * 1e3, before_s * 1e3,
                 "float" if keep else "int8")
        if keep:
            best = candidate
            kept.append(branch)
            kept_names += names
    record.update({"ran": True, "branches_tried": len(groups), "kept_float": kept, "steps": steps})
    return best, kept_names, record
