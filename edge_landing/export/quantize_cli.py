"""edge-quantize: static INT8 (QDQ) with an accuracy guard on held-out frames.

    edge-quantize model.onnx --calib scene/ --frames 16 --out model.int8.onnx
    edge-quantize model.onnx --calib scene/ --out model.int8.onnx --force        # keep it even if it fails
    edge-quantize model.onnx --calib suburban/ urban/ --frames 16 --out model.int8.onnx   # 8 + 8 frames

Exits non-zero with one line when INT8 loses more than the tolerance (the INT8 file is then not written).
Then INT8 is timed against FP32 on this CPU (interleaved, --threads) and the result is recorded in the
file with the CPU's ISA features: edge-run --precision auto uses INT8 only where it is faster.
Memory: ONNX Runtime's calibrator keeps every activation of every calibration frame (DenseDepth at 480x640:
4.6 GB peak with --frames 4), so use few frames for the big networks.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Sequence

from edge_landing.cli.common import CliParser, check_threads, output_file, run_cli
from edge_landing.runtime.core.errors import EdgeError

from .quant_speed import SpeedSearch
from .quantize import (
    CalibrationMethod,
    DepthHead,
    QuantFormat,
    QuantizeConfig,
    QuantKind,
    QuantReport,
    Tolerance,
    quantize,
)


class QuantizationRejected(EdgeError):
    """INT8 lost more accuracy than the tolerance allows."""


def build_parser() -> argparse.ArgumentParser:
    t = Tolerance()
    # ONNX Runtime's quantizer edits the graph with the onnx package; tqdm draws the bars (no torch needed)
    p = CliParser(prog="edge-quantize", description=__doc__.split("\n\n")[0], extra="export",
                  extra_modules=("onnx", "tqdm"))
    p.add_argument("model", type=Path, help="FP32 .onnx with the model contract (from edge-export)")
    p.add_argument("--calib", type=Path, nargs="+", required=True,
                   help="scene folder(s): each one's first frames calibrate, the following ones are held out for the "
                        "check (a model for several kinds of scene: give one of each)")
    p.add_argument("--frames", type=int, default=16, help="calibration frames in all, shared by the scenes (default 16)")
    p.add_argument("--eval-frames", type=int, default=16, help="held-out frames compared (default 16)")
    p.add_argument("--out", type=Path, required=True, help="INT8 .onnx to write")
    p.add_argument("--force", action="store_true", help="write the INT8 model even if it fails the tolerance")
    head = p.add_mutually_exclusive_group()
    head.add_argument("--keep-depth-head-float", dest="depth_head", action="store_const", const=DepthHead.FLOAT,
                      help="keep the last conv(s) feeding the depth output in float (default for depth models)")
    head.add_argument("--quantize-depth-head", dest="depth_head", action="store_const", const=DepthHead.INT8,
                      help="quantize the depth head too")
    p.set_defaults(depth_head=DepthHead.AUTO)
    p.add_argument("--method", default="minmax", help="calibration: minmax (default), entropy, percentile")
    p.add_argument("--no-per-channel", action="store_true", help="per-tensor weight scales")
    p.add_argument("--format", default="qdq", help="qdq (default) or qoperator (QLinearConv etc. in the file)")
    p.add_argument("--activations", default="u8", help="activation type: u8 (default) or s8")
    p.add_argument("--weights", default="s8", help="weight type: s8 (default) or u8")
    p.add_argument("--no-reduce-range", action="store_true", help="8-bit weights (only for VNNI CPUs)")
    p.add_argument("--exclude-node", action="append", default=[], help="keep this node in float (repeatable)")
    p.add_argument("--float-op-type", action="append", default=None,
                   help="keep every node of this op type float (repeatable; default: per architecture, "
                        "ConvTranspose, and MatMul/Gemm for AdaBins)")
    p.add_argument("--no-subpixel", action="store_true",
                   help="keep ConvTranspose as it is (default: rewrite it as Conv + DepthToSpace so it quantizes)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--no-speed-gate", action="store_true",
                   help="do not time INT8 against FP32 on this CPU (default: timed, recorded with the CPU's features)")
    p.add_argument("--speed-search", default="auto",
                   help="leave in float the top-level branches that are slower in INT8 on this CPU, found by timing: "
                        "auto (default: only when full INT8 is under 1.3x FP32 here), always, never")
    p.add_argument("--max-delta1-drop", type=float, default=t.max_delta1_drop)
    p.add_argument("--max-absrel-increase", type=float, default=t.max_abs_rel_increase)
    p.add_argument("--min-depth-agreement", type=float, default=t.min_depth_agreement)
    p.add_argument("--max-miou-drop", type=float, default=t.max_miou_drop)
    p.add_argument("--max-hprec-drop", type=float, default=t.max_hprec_drop)
    p.add_argument("--min-label-agreement", type=float, default=t.min_label_agreement)
    p.add_no_progress()
    return p


def _fmt(v: float) -> str:
    return "nan" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.4f}"


def format_report(report: QuantReport) -> str:
    c = report.comparison
    lines = [f"INT8 vs FP32 on {c['frames']} held-out frame(s) ({c['first']}..{c['last']}); "
             f"size {report.size_fp32_mb:.2f} MB -> {report.size_int8_mb:.2f} MB"]
    if "depth" in c:
        d = c["depth"]
        lines.append(f"  depth vs {d['reference']}: δ1 {_fmt(d['fp32']['a1'])} -> {_fmt(d['int8']['a1'])} "
                     f"(drop {_fmt(d['delta1_drop'])}), AbsRel {_fmt(d['fp32']['abs_rel'])} -> "
                     f"{_fmt(d['int8']['abs_rel'])} (increase {_fmt(d['abs_rel_increase'])}), "
                     f"within 5 % of FP32: {_fmt(d['agreement'])}")
    if "hvo" in c:
        h = c["hvo"]
        lines.append(f"  HVO vs {h['reference']}: mIoU {_fmt(h['fp32']['miou'])} -> {_fmt(h['int8']['miou'])} "
                     f"(drop {_fmt(h['miou_drop'])}), horizontal precision {_fmt(h['fp32']['horizontal_precision'])}"
                     f" -> {_fmt(h['int8']['horizontal_precision'])} (drop {_fmt(h['hprec_drop'])}), "
                     f"same label as FP32: {_fmt(h['agreement'])}")
    excluded = report.settings.get("excluded_nodes", [])
    st = report.settings
    lines.append(f"  settings: {st['format']} {st['activations']} activations / {st['weights']} weights, "
                 f"per_channel={st['per_channel']}, "
                 f"{report.settings.get('subpixel_conv_transposes', 0)} ConvTranspose(s) rewritten as Conv, "
                 f"reduce_range={report.settings['reduce_range']}; kept float: {len(excluded)} named node(s) and "
                 f"op type(s) {', '.join(report.settings['float_op_types']) or 'none'}")
    speed = report.settings.get("speed")
    if speed:
        verdict = ("faster" if speed["faster_here"] else
                   "NOT faster: edge-run --precision auto keeps FP32 on this CPU")
        lines.append(f"  speed on this CPU ({speed['cpu']}), {speed['threads']} thread(s), p50: INT8 "
                     f"{speed['int8_p50_ms']:.2f} ms vs FP32 {speed['fp32_p50_ms']:.2f} ms = "
                     f"{speed['int8_vs_fp32']:.2f}x, {verdict}")
    search = report.settings.get("speed_search", {})
    if search.get("ran"):
        lines.append(f"  speed search over {search['branches_tried']} branch(es): kept float "
                     f"{', '.join(search['kept_float']) or 'none'} (full INT8 was {search['int8_vs_fp32_full']:.2f}x FP32)")
    if "hvo" in c and _fmt(c["hvo"]["fp32"]["horizontal_precision"]) == "nan":
        lines.append("  note: horizontal precision is nan because the FP32 model predicts no horizontal pixel on "
                     "these frames (random or untrained weights?)")
    return "\n".join(lines)


def main_body(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    output_file(args.out, "the --out file")
    if args.threads is not None:
        check_threads("--threads", args.threads)
    tol = Tolerance(args.max_delta1_drop, args.max_absrel_increase, args.min_depth_agreement,
                    args.max_miou_drop, args.max_hprec_drop, args.min_label_agreement)
    config = QuantizeConfig(calib_scene=tuple(args.calib), calib_frames=args.frames, eval_frames=args.eval_frames,
                            per_channel=not args.no_per_channel, reduce_range=not args.no_reduce_range,
                            quant_format=QuantFormat.from_string(args.format),
                            activation_type=QuantKind.from_string(args.activations),
                            weight_type=QuantKind.from_string(args.weights),
                            method=CalibrationMethod.from_string(args.method), depth_head=args.depth_head,
                            exclude_nodes=tuple(args.exclude_node),
                            float_op_types=tuple(args.float_op_type) if args.float_op_type is not None else None,
                            subpixel=not args.no_subpixel, tolerance=tol, force=args.force,
                            threads=args.threads, progress=not args.no_progress, speed_gate=not args.no_speed_gate,
                            speed_search=SpeedSearch.from_string(args.speed_search))
    report = quantize(args.model, args.out, config)
    print(format_report(report))
    if not report.passed and not report.written:
        raise QuantizationRejected(f"INT8 model rejected: {'; '.join(report.reasons)}; {args.out} not written, "
                                   f"{args.model} untouched (use --force to keep it anyway)")
    if not report.passed:
        print(f"warning: INT8 fails the tolerance ({'; '.join(report.reasons)}); written anyway (--force)")
    print(f"wrote {args.out}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(main_body, argv)
