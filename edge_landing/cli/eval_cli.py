"""``edge-eval MODEL.onnx [MODEL2.onnx …] SCENE``: the paper's tables for ONNX models on a scene folder.

Prints Table 2/5-style depth rows (raw; ``*`` = per-image median-scaled; ``cal`` = per-scene calibrated
with ``--calibration``), Table 3/6-style SSIM and Median Rel, Table 4/7-style HVO per class; ``--paper``
adds the published rows; ``--json`` writes every figure (per frame too); ``--figures`` a qualitative grid.
"""
from __future__ import annotations

import argparse
import json
import math
from typing import Any, Callable, Optional, Sequence, Tuple

from edge_landing.cli.common import (
    CliParser,
    check_number,
    check_outputs_spare_inputs,
    check_threads,
    output_file,
    output_folder,
    run_cli,
)
from edge_landing.evaluation.evaluate import (
    EvalConfig,
    evaluate_scene,
    qualitative_grid,
)
from edge_landing.evaluation.metrics import Averaging
from edge_landing.evaluation.paper_tables import PaperDataset, PaperTables, paper_tables
from edge_landing.evaluation.scene import Scene
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.labels import HVO_CLASSES
from edge_landing.runtime.perception.calibration_file import (
    load_calibration,
    read_calibration,
)
from edge_landing.runtime.perception.inference import OnnxModel

DEPTH_COLUMNS = (("δ1", "a1"), ("δ2", "a2"), ("δ3", "a3"), ("AbsRel", "abs_rel"), ("SqRel", "sq_rel"),
                 ("RMS", "rms"), ("RMSlog", "rms_log"), ("log10", "log10"), ("SIlog", "silog"))
HVO_COLUMNS = (("accuracy", "accuracy"), ("precision", "precision"), ("recall", "recall"), ("IoU", "iou"))


def build_parser() -> argparse.ArgumentParser:
    p = CliParser(prog="edge-eval", description=__doc__.split("\n\n")[0],
                  usage="edge-eval MODEL.onnx [MODEL2.onnx ...] SCENE [options]",
                  formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paths", nargs="+", metavar="PATH", help="one or more models, then the scene folder")
    p.add_argument("--calibration", action="append", default=[], metavar="FILE",
                   help="per-scene calibration.json (edge-calibrate); repeat for several models: each file is "
                        "matched to the model whose sha256 it names")
    p.add_argument("--json", metavar="OUT", help="write every figure (and per-frame ones) to this JSON file")
    p.add_argument("--figures", metavar="DIR", help="write a qualitative grid PNG into this folder")
    p.add_argument("--figure-frames", type=int, default=4, metavar="N", help="frames in the grid (default 4)")
    p.add_argument("--paper", nargs="?", const="airsimnc", choices=[d.value for d in PaperDataset],
                   help="print the paper's rows beside, labelled as another dataset's (not comparable: other images "
                        "and base rates) (airsimnc = Tables 5–7, default; safeuav = Tables 2–4); "
                        "give it after the paths or as --paper=SET")
    p.add_argument("--min-depth", type=float, default=None,
                   help="valid ground truth above this, metres (default: the models' contract min_depth)")
    p.add_argument("--max-depth", type=float, default=None,
                   help="valid ground truth below this, metres (default: the models' contract max_depth; "
                        "80 is the KITTI/AdaBins convention)")
    p.add_argument("--averaging", default="per-image", choices=[a.value for a in Averaging],
                   help="depth: mean of per-image metrics (AdaBins, default) or global over all pixels")
    p.add_argument("--hvo-averaging", default="global", choices=[a.value for a in Averaging],
                   help="HVO: one confusion matrix for the scene (default) or mean of per-image figures")
    p.add_argument("--max-frames", type=int, default=None, help="evaluate the first N frames only")
    p.add_argument("--threads", type=int, default=2, help="ONNX Runtime threads (default 2)")
    p.add_no_progress()
    return p


def _fmt(v: Optional[float]) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.3f}"


def _table(title: str, header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    line: Callable[[Sequence[str]], str] = lambda r: "  ".join(
        str(c).ljust(w) if i == 0 else str(c).rjust(w) for i, (c, w) in enumerate(zip(r, widths)))
    return "\n".join([title, line(header), "-" * len(line(header)), *(line(r) for r in rows)])


PAPER_SOURCE = {PaperDataset.AIRSIMNC: "AirSimNC, the paper's zero-shot set rendered in AirSim",
                PaperDataset.SAFEUAV: "SafeUAV's Google-Earth-derived set"}


def _paper_tag(paper: PaperTables) -> str:
    return f"[{paper.dataset.value}: other dataset]"


def honest_table(hvo_models: Sequence[dict[str, Any]]) -> str:
    """Horizontal precision beside its base rate and lift, mIoU, and the landing figure (when scored)."""
    rows = []
    for m in hvo_models:
        b = m["hvo"]["baseline"]
        land = m.get("landable") or {}
        rows.append([m["name"], _fmt(b["horizontal_precision"]), _fmt(b["horizontal_base_rate"]),
                     _fmt(b["horizontal_lift"]), _fmt(b.get("horizontal_max_lift")), _fmt(b["miou"]),
                     _fmt(land.get("landable_precision")), _fmt(land.get("landable_base_rate")), _fmt(land.get("landable_lift")),
                     _fmt(land.get("called_share"))])
    return _table("Honest figures: H precision vs its base rate (share of labelled pixels that are horizontal = the "
                  "precision of calling everything horizontal) and the lift over it (max lift = a perfect net's); "
                  "mIoU; landable precision = share of pixels the runtime's fuser calls landable that the same fuser "
                  "on the ground truth finds landable "
                  "(– = no poses.csv/ground truth), beside its base rate",
                  ["model", "H prec", "H base", "H lift", "max lift", "mIoU", "land prec", "land base", "land lift",
                   "called"], rows)


def format_tables(result: dict[str, Any], paper: Optional[PaperTables] = None) -> str:
    """The console report: depth, SSIM/Median Rel, HVO (only the tables the models and scene allow)."""
    cfg = result["config"]
    out = [f"scene {result['scene']}: {result['frames']} frames; valid depth {cfg['min_depth_m']:g}–"
           f"{cfg['max_depth_m']:g} m" + (f" (from {cfg['depth_range_source']})" if cfg.get("depth_range_source") else "")
           + f", depth averaged {cfg['depth_averaging']}, HVO {cfg['hvo_averaging']}"]
    px = result.get("depth_pixels")
    if px and px["finite"] and px["in_range"] < 0.8 * px["finite"]:
        out.append(f"note: only {px['in_range'] / px['finite']:.0%} of the finite ground-truth depth lies in "
                   f"({cfg['min_depth_m']:g}, {cfg['max_depth_m']:g}) m; the rest is not scored "
                   f"(widen with --max-depth)")
    depth_models = [m for m in result["models"] if m["depth"]]
    hvo_models = [m for m in result["models"] if m["hvo"]]
    if depth_models:
        rows = []
        for prefix, key in (("", "raw"), ("* ", "median_scaled"), ("cal ", "calibrated")):
            for m in depth_models:
                if m["depth"][key] is not None:
                    rows.append([prefix + m["name"], *(_fmt(m["depth"][key][k]) for _, k in DEPTH_COLUMNS)])
        if paper is not None:
            for r in paper.depth:
                rows.append([f"paper {'* ' if r.median_scaled else ''}{r.model} {_paper_tag(paper)}", _fmt(r.a1), _fmt(r.a2),
                             _fmt(r.a3), _fmt(r.abs_rel), "–", _fmt(r.rms), "–", _fmt(r.log10), "–"])
        n = paper.table_numbers[0] if paper else "2/5"
        out += ["", _table(f"Depth (Table {n} style; plain = raw model output, * = per-image median-scaled, "
                           f"cal = per-scene calibrated; RMS in m, the rest unitless)",
                           ["model", *(c for c, _ in DEPTH_COLUMNS)], rows)]
        scale_rows = []
        for m in depth_models:
            d = m["depth"]
            ms = d["median_scale"] or {}
            scale_rows.append([m["name"], _fmt(ms.get("median")), _fmt(ms.get("min")), _fmt(ms.get("max")),
                               _fmt(d["calibration"]["scale"]) if d["calibration"] else "–"])
        out += ["", _table("Per-image median-scale ratios (gt/pred) and the per-scene calibration used "
                           "(– = no --calibration file for that model)",
                           ["model", "median", "min", "max", "calibration"], scale_rows)]
        rows = [[m["name"], _fmt(m["depth"]["ssim"]), _fmt(m["depth"]["median_rel"])] for m in depth_models]
        if paper is not None:
            rows += [[f"paper {r.model} {_paper_tag(paper)}", _fmt(r.ssim), _fmt(r.median_rel)] for r in paper.ssim]
        n = paper.table_numbers[1] if paper else "3/6"
        out += ["", _table(f"SSIM and Median Rel (Table {n} style; Median Rel > 0 = predictions shorter)",
                           ["model", "SSIM", "Median Rel"], rows)]
    if hvo_models:
        rows = []
        for m in hvo_models:
            for cls in (*HVO_CLASSES, "average"):
                rows.append([m["name"], cls, *(_fmt(m["hvo"][cls][k]) for _, k in HVO_COLUMNS)])
        if paper is not None:
            order = (*HVO_CLASSES, "average")  # the paper lists other before vertical; print in our order
            models = list(dict.fromkeys(r.model for r in paper.hvo))
            ranked = sorted(paper.hvo, key=lambda r: (models.index(r.model),
                                                     order.index(r.cls) if r.cls in order else len(order)))
            rows += [[f"paper {r.model} {_paper_tag(paper)}", r.cls, _fmt(r.accuracy), _fmt(r.precision), _fmt(r.recall),
                      _fmt(r.iou)] for r in ranked]
        n = paper.table_numbers[2] if paper else "4/7"
        out += ["", _table(f"HVO, each class against the rest (Table {n} style)",
                           ["model", "class", *(c for c, _ in HVO_COLUMNS)], rows)]
        out += ["", honest_table(hvo_models)]
    if paper is not None:
        out += ["", f"note: rows marked 'paper … {_paper_tag(paper)}' are the paper's published figures on another "
                    f"dataset ({paper.dataset.value}: {PAPER_SOURCE[paper.dataset]}), other images, labels and base "
                    f"rates; they are NOT comparable with this scene's rows, only printed for reference"]
    for m in result["models"]:
        if not m["depth"] and not m["hvo"]:
            out.append(f"\nnote: {m['name']} ({m['task']}) has nothing to be scored against in this scene")
        if m["invalid_frames"]:
            out.append(f"\nwarning: {m['name']} gave invalid output on {len(m['invalid_frames'])} frame(s), "
                       f"e.g. {m['invalid_frames'][0]}")
    return "\n".join(out)


def _match_calibrations(files: Sequence[str], models: Sequence[OnnxModel]) -> tuple[dict[int, float], dict[int, str]]:
    """Pair each calibration file with the model whose sha256 it names (one model: used, with a warning if
    the sha differs). Returns (scales, files) keyed by model index."""
    scales: dict[int, float] = {}
    names: dict[int, str] = {}
    for f in files:
        if len(models) == 1:
            scales[0], names[0] = load_calibration(f, model_sha256=models[0].sha256), f
            continue
        cal = read_calibration(f)
        idx = [i for i, m in enumerate(models) if m.sha256 == cal.model_sha256]
        if not idx:
            raise InputError(f"calibration file {f} names model {cal.model_sha256[:12]}… ({cal.model_path}), "
                             f"which is none of the models given")
        for i in idx:
            scales[i], names[i] = load_calibration(f, model_sha256=models[i].sha256), f
    return scales, names


def _depth_range(args: argparse.Namespace, models: Sequence[OnnxModel]) -> Tuple[float, float, str]:
    """The scored ground-truth range: the flags where given, else the range every depth model's contract
    (``edge.depth`` min/max) covers, so no pixel is scored against a prediction that can only be clamped."""
    specs = [m.contract.depth for m in models if m.contract.depth is not None]
    lo = max((s.min_depth for s in specs), default=EvalConfig.min_depth_m)
    hi = min((s.max_depth for s in specs), default=EvalConfig.max_depth_m)
    if lo >= hi:
        lo, hi = EvalConfig.min_depth_m, EvalConfig.max_depth_m
    src = "the models' contract (edge.depth min/max)" if specs else "the default range"
    if args.min_depth is not None or args.max_depth is not None:
        src = "--min-depth/--max-depth" + (f", the rest from {src}" if None in (args.min_depth, args.max_depth) else "")
    return (args.min_depth if args.min_depth is not None else lo,
            args.max_depth if args.max_depth is not None else hi, src)


def _json_safe(obj: Any) -> Any:
    """NaN/inf -> null, so the file is strict JSON."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj


def _main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    if len(args.paths) < 2:
        raise InputError(f"edge-eval needs at least one model and a scene folder, got only '{args.paths[0]}' "
                         f"(usage: edge-eval MODEL.onnx [MODEL2.onnx …] SCENE)")
    *model_paths, scene_path = args.paths
    check_threads("--threads", args.threads)
    for flag, value in (("--min-depth", args.min_depth), ("--max-depth", args.max_depth)):
        if value is not None:
            check_number(flag, value, 0.0, lo_open=True, unit="metres")
    if args.figure_frames < 1:
        raise InputError(f"--figure-frames must be at least 1, got {args.figure_frames}")
    # where the results go is settled before the work, so a bad path does not lose the figures afterwards
    check_outputs_spare_inputs({"--json": args.json}, {f"model {p}": p for p in model_paths})
    json_path = output_file(args.json, "the --json file") if args.json else None
    figures_dir = output_folder(args.figures, "the --figures folder") if args.figures else None
    scene = Scene(scene_path)
    models = [OnnxModel.load(p, threads=args.threads) for p in model_paths]
    min_depth_m, max_depth_m, range_source = _depth_range(args, models)
    config = EvalConfig(min_depth_m, max_depth_m, Averaging.from_string(args.averaging),
                        Averaging.from_string(args.hvo_averaging), args.max_frames)
    scales, cal_files = _match_calibrations(args.calibration, models)
    result = evaluate_scene(models, scene, config, scales, cal_files, show_progress=not args.no_progress)
    result["config"]["depth_range_source"] = range_source
    paper = paper_tables(args.paper) if args.paper else None
    print(format_tables(result, paper))
    for kind, needed, present in (("depth", "has_depth", scene.has_depth), ("hvo", "has_hvo", scene.has_hvo)):
        if not present and any(getattr(m.contract.task, needed) for m in models):
            print(f"note: scene {scene.path} has no {kind}/ ground truth; the models' {kind} output is not scored")
    if json_path is not None:
        if paper is not None:
            result["paper"] = paper.to_json()
        path = json_path
        try:
            path.write_text(json.dumps(_json_safe(result), indent=1))
        except OSError as exc:
            raise InputError(f"cannot write --json file {path}: {exc.strerror}") from None
        print(f"\nwrote {path}")
    if figures_dir is not None:
        import cv2

        out_dir = figures_dir
        frames = scene.frame_ids[: max(1, args.figure_frames)]
        grid = qualitative_grid(models, scene, frames)
        png = out_dir / f"qualitative_{scene.path.resolve().name}.png"
        if not cv2.imwrite(str(png), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR)):
            raise InputError(f"could not write figure {png}")
        print(f"wrote {png}")
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
