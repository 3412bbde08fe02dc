"""What ONNX Runtime's quantizer offers, on this CPU: one table of INT8 variants of one FP32 model (§9).

    python -m edge_landing.benchmarks.quant_variants MODEL.onnx --calib SCENE [SCENE ...] --out out/qv_edgenet
    python -m edge_landing.benchmarks.quant_variants safeuav-small --calib SCENE --out out/qv_small

Each variant (activation/weight types U8/S8, per-channel or per-tensor, reduce_range, QDQ or QOperator, and
the default plus edge-quantize's branch search) is quantized with edge-quantize's pipeline (same calibration
frames, same held-out frames, --force so that every variant is timed), then FP32, every variant and
OpenVINO (when installed) on the FP32 and default INT8 files are timed round-robin in one run after warm-up.
Prints a markdown table with the CPU's ISA features; writes variants.json under --out. A zoo name instead
of a file exports that architecture at its paper size with random weights (agreement is then between two
random-weight nets: only a sanity check).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import List, Optional, Sequence

from edge_landing.cli.common import CliParser, check_threads, output_folder, run_cli
from edge_landing.runtime.core.cpu_features import cpu_features
from edge_landing.runtime.core.errors import ContractError, InputError, SceneError


@dataclass(frozen=True)
class Variant:
    name: str
    format: str = "qdq"
    activations: str = "u8"
    weights: str = "s8"
    per_channel: bool = True
    reduce_range: bool = True
    search: str = "never"


VARIANTS = (
    Variant("QDQ U8/S8 per-channel reduce_range (edge-quantize default)"),
    Variant("QDQ U8/S8 per-channel, full-range weights", reduce_range=False),
    Variant("QDQ U8/S8 per-tensor reduce_range", per_channel=False),
    Variant("QDQ S8/S8 per-channel reduce_range", activations="s8"),
    Variant("QDQ U8/U8 per-channel reduce_range", weights="u8"),
    Variant("QOperator U8/S8 per-channel reduce_range", format="qoperator"),
    Variant("QOperator S8/S8 per-channel reduce_range", format="qoperator", activations="s8"),
    Variant("default + branch search (always)", search="always"),
)


def _fp32_file(model: str, out: Path) -> Path:
    if Path(model).is_file():
        return Path(model)
    from edge_landing.benchmarks.catalog import CATALOG
    from edge_landing.export.onnx_export import ExportSettings, export_onnx
    from edge_landing.export.zoo import get_arch

    if model not in CATALOG:
        raise InputError(f"{model} is neither an .onnx file nor a zoo model ({', '.join(CATALOG)})")
    m = CATALOG[model]
    spec = get_arch(m.arch)
    path = out / f"{model}.onnx"
    if not path.exists():
        export_onnx(spec, m.task, path, *spec.input_hw, options=dict(m.options), settings=ExportSettings(progress=False))
    return path


def quantize_variants(fp32: Path, calib: List[Path], out: Path, frames: int, eval_frames: int) -> List[dict]:
    from edge_landing.export.quant_speed import SpeedSearch
    from edge_landing.export.quantize import QuantFormat, QuantizeConfig, QuantKind, quantize

    base = QuantizeConfig(calib_scene=tuple(calib), calib_frames=frames, eval_frames=eval_frames, force=True,
                          progress=False, speed_gate=False)
    rows: List[dict] = []
    for i, v in enumerate(VARIANTS):
        cfg = replace(base, quant_format=QuantFormat.from_string(v.format),
                      activation_type=QuantKind.from_string(v.activations), weight_type=QuantKind.from_string(v.weights),
                      per_channel=v.per_channel, reduce_range=v.reduce_range,
                      speed_gate=v.search != "never", speed_search=SpeedSearch.from_string(v.search))
        path = out / f"variant{i}.int8.onnx"
        try:
            report = quantize(fp32, path, cfg)
        except Exception as exc:  # a variant ONNX Runtime cannot build is a row of the table, not the end
            rows.append({"variant": v.name, "error": str(exc).splitlines()[0][:160]})
            continue
        c = report.comparison
        rows.append({"variant": v.name, "path": str(path), "passed": report.passed,
                     "depth_agreement": c.get("depth", {}).get("agreement"),
                     "hvo_agreement": c.get("hvo", {}).get("agreement"),
                     "kept_float": report.settings.get("speed_search", {}).get("kept_float"),
                     "size_mb": report.size_int8_mb})
    return rows


def time_all(fp32: Path, rows: List[dict], threads: int, iterations: int) -> dict:
    from edge_landing.runtime.perception.inference import read_contract

    from .speed import SpeedConfig, interleaved, openvino_available, openvino_backend, ort_backend

    contract = read_contract(fp32)
    backends = [ort_backend(fp32, contract, threads, "ort-fp32", name="ORT FP32")]
    backends += [ort_backend(r["path"], contract, threads, "ort-int8", name=r["variant"]) for r in rows if "path" in r]
    if openvino_available():   # each file first compiled and run in a child: OpenVINO can crash, not raise
        from edge_landing.runtime.perception.openvino_check import runs_in_child

        for path, kind, name in ((fp32, "openvino", "OpenVINO FP32 (same FP32 file)"),
                                 (rows[0].get("path"), "openvino-int8", "OpenVINO INT8 (default QDQ file)")):
            ok, why = runs_in_child(path, threads) if path is not None else (False, "no default INT8 file")
            if ok and path is not None:
                backends.append(openvino_backend(path, contract, threads, kind=kind, name=name))
            else:
                print(f"quant_variants: {name} not timed: {why}", file=sys.stderr)
    timings = interleaved(backends, SpeedConfig(warmup=5, iterations=iterations, max_seconds=240.0, progress=False))
    return {name: t.to_json() for name, t in timings.items()}


def to_markdown(result: dict) -> str:
    t, fp32_ips = result["timings"], result["timings"]["ORT FP32"]["images_per_s"]
    lines = [f"{result['model']} ({result['input']}), {result['threads']} threads, {result['iterations']} interleaved "
             f"rounds; CPU: {result['cpu']}; ONNX Runtime {result['onnxruntime']}", "",
             "| variant | images/s | p50/p90/p99 ms | × ORT FP32 (images/s) | × ORT FP32 (p50) | depth agrees | "
             "HVO agrees | gate |", "|---|---|---|---|---|---|---|---|"]
    fp32_p50 = t["ORT FP32"]["p50_ms"]

    def fmt(v: Optional[float]) -> str:
        return "–" if v is None else f"{v:.3f}"

    named = [{"variant": "ORT FP32"}] + result["variants"] + [
        {"variant": n} for n in t if n.startswith("OpenVINO")]
    for r in named:
        name = r["variant"]
        if "error" in r:
            lines.append(f"| {name} | failed: {r['error']} | | | | | | |")
            continue
        x = t[name]
        extra = f" (kept float: {', '.join(r['kept_float']) or 'none'})" if r.get("kept_float") is not None else ""
        gate = "–" if "passed" not in r else ("pass" if r["passed"] else "FAIL")
        lines.append(f"| {name}{extra} | {x['images_per_s']:.1f} | {x['p50_ms']:.2f}/{x['p90_ms']:.2f}/"
                     f"{x['p99_ms']:.2f} | {x['images_per_s'] / fp32_ips:.2f}× | {fp32_p50 / x['p50_ms']:.2f}× | "
                     f"{fmt(r.get('depth_agreement'))} | "
                     f"{fmt(r.get('hvo_agreement'))} | {gate} |")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = CliParser(prog="quant_variants", description=__doc__.split("\n\n")[0], extra="bench",
                  extra_modules=("onnx", "tqdm"))
    p.add_argument("model", help="FP32 .onnx with the contract, or a zoo model name (random weights)")
    p.add_argument("--calib", type=Path, nargs="+", required=True, help="scene folder(s), as for edge-quantize")
    p.add_argument("--frames", type=int, default=16)
    p.add_argument("--eval-frames", type=int, default=16)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--iterations", type=int, default=60)
    p.add_argument("--out", type=Path, required=True)
    return p


def check_args(a: argparse.Namespace) -> None:
    """Everything every variant shares, checked once before the first: a bad --calib or frame count is the
    user's error, not a failed row per variant."""
    from edge_landing.evaluation.scene import Scene
    from edge_landing.export.calib_frames import split_frames

    for flag, value in (("--frames", a.frames), ("--eval-frames", a.eval_frames), ("--iterations", a.iterations)):
        if value < 1:
            raise InputError(f"{flag} must be at least 1, got {value}")
    check_threads("--threads", a.threads)
    try:
        split_frames([Scene(p) for p in a.calib], a.frames, a.eval_frames)
    except SceneError as exc:
        raise InputError(f"--calib: {exc}") from None


def _main(argv: Optional[Sequence[str]] = None) -> int:
    import onnxruntime

    a = build_parser().parse_args(argv)
    check_args(a)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    output_folder(a.out, "the --out folder")
    fp32 = _fp32_file(a.model, a.out)
    from edge_landing.runtime.perception.inference import read_contract

    try:
        c = read_contract(fp32)          # before any variant: a broken model is one line, not eight failed rows
    except ContractError as exc:
        raise InputError(f"model: {exc}") from None
    rows = quantize_variants(fp32, list(a.calib), a.out, a.frames, a.eval_frames)
    result = {"model": Path(a.model).name, "input": f"{c.input.height}x{c.input.width}", "threads": a.threads,
              "iterations": a.iterations, "cpu": cpu_features().summary(), "isa": cpu_features().to_json(),
              "onnxruntime": onnxruntime.__version__, "load_average": list(os.getloadavg()), "variants": rows,
              "timings": time_all(fp32, rows, a.threads, a.iterations)}
    (a.out / "variants.json").write_text(json.dumps(result, indent=1, default=str))
    print(to_markdown(result))
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
