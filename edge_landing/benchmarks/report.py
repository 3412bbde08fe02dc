"""Table 1-style speed report: rows in, markdown / JSON / CSV / PNG out.

One :class:`BenchRow` per model; its ``timings`` map a backend kind (``ort-fp32``, ``ort-int8``, ``torch``,
``openvino``, ``openvino-int8``, ``openvino-default``) to the JSON of a :class:`benchmarks.speed.Timing`. The report JSON is::

    {"schema": 1, "machine": {...}, "peak": {...}, "settings": {...}, "notes": [...], "rows": [BenchRow, ...]}
"""
from __future__ import annotations

import csv
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

SCHEMA_VERSION = 1
KIND_ORDER = ("ort-fp32", "ort-int8", "torch", "openvino", "openvino-int8", "openvino-default")
KIND_LABEL = {"ort-fp32": "ORT FP32", "ort-int8": "ORT INT8", "torch": "PyTorch eager", "openvino": "OpenVINO FP32",
              "openvino-int8": "OpenVINO INT8", "openvino-default": "OpenVINO default precision"}
ROW_KEYS = ("model", "arch", "task", "input_hw", "threads", "params_m", "onnx_fp32_mb", "onnx_int8_mb", "gmac",
            "paper_v100_images_per_s", "timings", "int8_vs_fp32", "int8_vs_torch", "fp32_gflops",
            "fp32_share_of_peak", "int8_agreement", "scaling", "notes", "peak_gflops_same_run")


@dataclass
class BenchRow:
    model: str
    arch: str
    task: str
    input_hw: List[int]
    threads: int
    params_m: float
    onnx_fp32_mb: float
    onnx_int8_mb: Optional[float]
    gmac: float
    paper_v100_images_per_s: Optional[float]
    timings: Dict[str, dict]
    int8_vs_fp32: Optional[float] = None
    int8_vs_torch: Optional[float] = None
    fp32_gflops: Optional[float] = None
    fp32_share_of_peak: Optional[float] = None
    int8_agreement: Optional[float] = None       # share of HVO labels / depth pixels INT8 agrees with FP32 on
    scaling: Dict[str, dict] = field(default_factory=dict)   # kind -> {"1": ips, "2": ips, "speedup": x}
    notes: List[str] = field(default_factory=list)
    profile: Dict[str, list] = field(default_factory=dict)   # kind -> [OpTime json, ...] (edge-bench --profile)
    peak_gflops_same_run: Optional[float] = None   # best run of the matmul probe timed in the model's round-robin
    paper_model_mb: Optional[float] = None         # Table 1's model size (the authors' files)

    def ips(self, kind: str) -> Optional[float]:
        t = self.timings.get(kind)
        return t["images_per_s"] if t else None

    def finish(self, peak_gflops: Optional[float] = None) -> BenchRow:
        """Derived columns: INT8 ratios from the same interleaved run, achieved GFLOP/s and its share of
        ``peak_gflops`` (the best matmul throughput seen in the whole session)."""
        fp32, int8, torch = self.ips("ort-fp32"), self.ips("ort-int8"), self.ips("torch")
        if fp32 and int8:
            self.int8_vs_fp32 = int8 / fp32
        if torch and int8:
            self.int8_vs_torch = int8 / torch
        if fp32:
            self.fp32_gflops = 2.0 * self.gmac * fp32
            if peak_gflops and math.isfinite(peak_gflops):
                self.fp32_share_of_peak = self.fp32_gflops / peak_gflops
        return self


def _f(value, digits: int = 2, suffix: str = "") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    return f"{value:.{digits}f}{suffix}"


def kinds_in(rows: List[BenchRow]) -> List[str]:
    present = {k for r in rows for k in r.timings}
    return [k for k in KIND_ORDER if k in present]


def to_markdown(report: dict) -> str:
    rows = [BenchRow(**r) for r in report["rows"]]
    kinds = kinds_in(rows)
    head = ["model", "input", "params (M)", "FP32 MB", "INT8 MB", "GMAC"]
    head += [f"{KIND_LABEL[k]} img/s (p50/p90/p99 ms)" for k in kinds]
    head += ["INT8/FP32", "INT8/torch", "FP32 GFLOP/s (% peak)", "INT8 agrees", "paper V100 img/s", "paper MB"]
    machine = report.get("machine", {})
    lines = [f"CPU: {machine.get('isa_summary', machine.get('cpu', 'unknown'))}; {machine.get('logical_cpus', '?')} "
             f"logical CPU(s); ONNX Runtime {machine.get('onnxruntime', '?')}", ""]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r.model, f"{r.input_hw[0]}×{r.input_hw[1]}", _f(r.params_m), _f(r.onnx_fp32_mb, 1),
                 _f(r.onnx_int8_mb, 1), _f(r.gmac, 1)]
        for k in kinds:
            t = r.timings.get(k)
            cells.append(f"{t['images_per_s']:.2f} ({t['p50_ms']:.0f}/{t['p90_ms']:.0f}/{t['p99_ms']:.0f})"
                         if t else "–")
        share = f" ({100 * r.fp32_share_of_peak:.0f} %)" if r.fp32_share_of_peak is not None else ""
        cells += [_f(r.int8_vs_fp32, 2, "×"), _f(r.int8_vs_torch, 2, "×"), _f(r.fp32_gflops, 1) + share,
                  _f(r.int8_agreement, 3), _f(r.paper_v100_images_per_s, 3), _f(r.paper_model_mb, 0)]
        lines.append("| " + " | ".join(cells) + " |")
    peak = report["peak"]
    lines.append("")
    same_run = ", ".join(f"{r.model} {r.peak_gflops_same_run:.1f}" for r in rows if r.peak_gflops_same_run)
    lines.append(f"{report['settings']['threads']} thread(s); backends timed round-robin in one run per model, ratios "
                 f"are within that run. FP32 peak = best 1024² matmul seen in the session: {peak['gflops']:.1f} "
                 f"GFLOP/s (stand-alone ORT {_f(peak.get('ort_gflops'), 1)}, numpy {_f(peak.get('numpy_gflops'), 1)}"
                 + (f"; probe inside each model's round-robin: {same_run}" if same_run else "") + ").")
    scaling = [(r.model, k, s) for r in rows for k, s in r.scaling.items()]
    if scaling:
        lines += ["", "| model | backend | 1 thread img/s | 2 threads img/s | speed-up |", "|---|---|---|---|---|"]
        lines += [f"| {m} | {KIND_LABEL.get(k, k)} | {_f(s.get('1'))} | {_f(s.get('2'))} | "
                  f"{_f(s.get('speedup'), 2, '×')} |" for m, k, s in scaling]
    for r in rows:
        for kind, ops in r.profile.items():
            top = ", ".join(f"{o['op_type']} {100 * o['share']:.0f} %" for o in ops[:4])
            lines.append(f"- {r.model} {KIND_LABEL.get(kind, kind)} kernel time: {top}")
    from .goals import check_goals

    goals = check_goals(report)
    if goals:
        lines += ["", "Goals (ratios from this run):"] + [g.line() for g in goals]
    lines += [f"- {n}" for n in report.get("notes", [])]
    lines += [f"- {r.model}: {n}" for r in rows for n in r.notes]
    return "\n".join(lines)


def write_json(report: dict, path: Path) -> Path:
    path.write_text(json.dumps(report, indent=2, sort_keys=True, default=_nan_to_none))
    return path


def _nan_to_none(value):
    return None if isinstance(value, float) and not math.isfinite(value) else str(value)


def write_csv(report: dict, path: Path) -> Path:
    """One line per (model, backend), with the model's columns repeated: easy to load in a spreadsheet."""
    fields = ["model", "arch", "task", "height", "width", "threads", "params_m", "onnx_fp32_mb", "onnx_int8_mb",
              "gmac", "paper_v100_images_per_s", "backend", "images_per_s", "p50_ms", "p90_ms", "p99_ms",
              "iterations", "int8_vs_fp32", "int8_vs_torch", "fp32_gflops", "fp32_share_of_peak", "int8_agreement",
              "peak_gflops_same_run"]
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        for raw in report["rows"]:
            r = BenchRow(**raw)
            for kind, t in r.timings.items():
                w.writerow({"model": r.model, "arch": r.arch, "task": r.task, "height": r.input_hw[0],
                            "width": r.input_hw[1], "threads": r.threads, "params_m": r.params_m,
                            "onnx_fp32_mb": r.onnx_fp32_mb, "onnx_int8_mb": r.onnx_int8_mb, "gmac": r.gmac,
                            "paper_v100_images_per_s": r.paper_v100_images_per_s, "backend": kind,
                            "images_per_s": t["images_per_s"], "p50_ms": t["p50_ms"], "p90_ms": t["p90_ms"],
                            "p99_ms": t["p99_ms"], "iterations": t["iterations"], "int8_vs_fp32": r.int8_vs_fp32,
                            "int8_vs_torch": r.int8_vs_torch, "fp32_gflops": r.fp32_gflops,
                            "fp32_share_of_peak": r.fp32_share_of_peak, "int8_agreement": r.int8_agreement,
                            "peak_gflops_same_run": r.peak_gflops_same_run})
    return path


def write_png(report: dict, path: Path) -> Path:
    """Grouped bars of images/s per model and backend (log scale), the paper's V100 figure hatched."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = [BenchRow(**r) for r in report["rows"]]
    series: List[tuple[str, List[float], Optional[str]]] = [
        (KIND_LABEL[k], [r.ips(k) or 0.0 for r in rows], None) for k in kinds_in(rows)]
    if any(r.paper_v100_images_per_s for r in rows):
        series.append(("V100 (paper)", [r.paper_v100_images_per_s or 0.0 for r in rows], "//"))
    x = np.arange(len(rows))
    width = 0.8 / max(len(series), 1)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.8 * len(rows) + 2), 4.5))
    for i, (label, values, hatch) in enumerate(series):
        ax.bar(x + (i - (len(series) - 1) / 2) * width, values, width, label=label, hatch=hatch,
               fill=hatch is None, edgecolor="black" if hatch else None)
    ax.set_xticks(x, [f"{r.model}\n{r.input_hw[0]}×{r.input_hw[1]}" for r in rows])
    ax.set_yscale("log")
    ax.set_ylabel("images/s")
    ax.set_title(f"Speed at {report['settings']['threads']} thread(s) (CPU) vs the paper's V100")
    ax.legend(fontsize=8)
    ax.grid(axis="y", which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def row_to_json(row: BenchRow) -> dict:
    return asdict(row)
