"""The project's speed goals, checked against a finished report (issues 5, 7 and 16; ARCHITECTURE.md §9).

Each check says whether the goal was met and, when not, by how much and where the time goes (the top
kernels of the profile when ``edge-bench --profile`` recorded one). The per-CPU goals of issue 16 are about
the configuration edge-run runs; the bench cannot run edge-run's accuracy gate and OpenVINO agreement check, so
they are checked on the fastest configuration edge-run *may* run (:data:`PICKABLE`) and say so.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import List, Optional

from .catalog import CATALOG, PEERS
from .report import KIND_ORDER

CONV_HEAVY = ("densedepth", "safeuav-large", "safeuav-small", "adabins-80", "adabins-256")
ZOO = tuple(name for name in CATALOG if name not in PEERS)
OPENVINO_KINDS = tuple(kind for kind in KIND_ORDER if kind.startswith("openvino"))
# What edge-run --precision auto --runtime auto chooses among (OpenVINO in f32; its own bf16 default is not one).
PICKABLE = ("ort-fp32", "ort-int8", "openvino", "openvino-int8")
_PICK_NOTE = "fastest of what edge-run may run"


@dataclass(frozen=True)
class GoalCheck:
    model: str
    goal: str
    value: float
    target: float
    met: bool
    detail: str = ""

    def to_json(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        verdict = "met" if self.met else f"MISSED by {100 * (1 - self.value / self.target):.0f} %"
        return f"- goal {self.model}: {self.goal}: {self.value:.2f} vs {self.target:.2f} -> {verdict}" + (
            f" ({self.detail})" if self.detail and not self.met else "")


def _at_least(model: str, goal: str, value: Optional[float], target: float, detail: str = "") -> List[GoalCheck]:
    if value is None:
        return []
    return [GoalCheck(model, goal, float(value), target, value >= target, detail)]


def _top_ops(row: dict, kind: str) -> str:
    ops = row.get("profile", {}).get(kind) or []
    return ", ".join(f"{o['op_type']} {100 * o['share']:.0f} %" for o in ops[:3])


def _ips(row: dict, kind: str) -> Optional[float]:
    value = row.get("timings", {}).get(kind, {}).get("images_per_s")
    return float(value) if value else None


def fastest_pickable(row: dict) -> Optional[tuple[str, float]]:
    """(kind, images/s) of the fastest configuration edge-run may run for this row, or None."""
    timed = [(k, v) for k in PICKABLE if (v := _ips(row, k)) is not None]
    return max(timed, key=lambda kv: kv[1]) if timed else None


def per_cpu_checks(rows: dict) -> List[GoalCheck]:
    """Issue 16: the pick >= 1.3x ORT FP32 for EdgeNet, never slower than FP32 on any zoo model, >= 2.5x PyTorch
    eager for SafeUAV-Net-Small, and >= the fastest OpenVINO configuration timed (its own default included)."""
    checks: List[GoalCheck] = []
    for name in ZOO:
        row = rows.get(name)
        best = fastest_pickable(row) if row else None
        fp32 = _ips(row, "ort-fp32") if row else None
        if row is None or best is None or fp32 is None:
            continue
        kind, ips = best
        detail = f"{_PICK_NOTE}: {kind}; INT8 and OpenVINO still need edge-run's gate and agreement check"
        checks += _at_least(name, f"{_PICK_NOTE} / ORT FP32", ips / fp32, 1.3 if name == "edgenet" else 1.0, detail)
        torch = _ips(row, "torch")
        if name == "safeuav-small" and torch:
            checks += _at_least(name, f"{_PICK_NOTE} / PyTorch eager", ips / torch, 2.5, detail)
        openvino = [(k, v) for k in OPENVINO_KINDS if (v := _ips(row, k))]
        if openvino:
            ov_kind, ov_ips = max(openvino, key=lambda kv: kv[1])
            checks += _at_least(name, f"{_PICK_NOTE} / fastest OpenVINO ({ov_kind})", ips / ov_ips, 1.0,
                                "OpenVINO's own default precision, which edge-run does not run (no gate checked it)"
                                if ov_kind == "openvino-default" else detail)
    return checks


def check_goals(report: dict) -> List[GoalCheck]:
    rows = {r["model"]: r for r in report["rows"]}
    checks: List[GoalCheck] = []
    small = rows.get("safeuav-small")
    if small:
        why = _top_ops(small, "ort-int8")
        why = f"INT8 kernel time: {why}" if why else "run with --profile to see where the INT8 time goes"
        checks += _at_least("safeuav-small", "ORT INT8 / ORT FP32", small.get("int8_vs_fp32"), 1.4, why)
        checks += _at_least("safeuav-small", "ORT INT8 / PyTorch eager", small.get("int8_vs_torch"), 2.5, why)
        checks += _at_least("safeuav-small", "INT8 labels agreeing with FP32", small.get("int8_agreement"), 0.9)
    for name in CONV_HEAVY:
        row = rows.get(name)
        if row:
            why = _top_ops(row, "ort-fp32")
            checks += _at_least(name, "ORT FP32 share of the matmul peak", row.get("fp32_share_of_peak"), 0.5,
                                f"FP32 kernel time: {why}" if why else "")
    edge = rows.get("edgenet")
    if edge:
        int8 = edge.get("timings", {}).get("ort-int8", {}).get("images_per_s")
        checks += _at_least("edgenet", "ORT INT8 images/s", int8, 60.0)
        small_int8 = small.get("timings", {}).get("ort-int8", {}).get("images_per_s") if small else None
        if int8 and small_int8:
            checks += _at_least("edgenet", "ORT INT8 images/s / SafeUAV-Net-Small INT8", int8 / small_int8, 1.0)
    return checks + per_cpu_checks(rows)
