"""edge-bench: a Table 1-style speed report of the zoo on this CPU (ARCHITECTURE.md §9).

    edge-bench                                   # default set (no AdaBins), paper input sizes, 2 threads
    edge-bench --models safeuav-small,adabins-80 --out bench/
    edge-bench --quick                           # one small model, few iterations (a smoke test)
    edge-bench --scaling                         # 1 vs 2 threads, all interleaved in one run

For each model: parameters, ONNX size FP32/INT8, and for ONNX Runtime FP32, ONNX Runtime INT8, PyTorch eager
(and OpenVINO FP32 and INT8 on the same two ONNX files when openvino is installed) images/s and p50/p90/p99
latency after warm-up, all backends timed round-robin in one run; the CPU's ISA features above the table;
achieved GFLOP/s (MACs counted from the ONNX graph) against the FP32 matmul peak probed in the same run; the
paper's V100 images/s beside. Markdown on stdout, report.json, report.csv and report.png under --out.
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

from edge_landing.cli.common import CliParser, check_number, check_threads, output_folder, run_cli
from edge_landing.evaluation.scene import Scene
from edge_landing.runtime.core.errors import InputError

from . import report as rep
from .catalog import DEFAULT_MODELS, PEERS, QUICK_MODELS, PrepareConfig, lookup, prepare
from .goals import check_goals
from .speed import SpeedConfig

DEFAULT_OUT = Path("out/bench")   # /out/ is git-ignored
MAX_SIDE = 4096                   # --height/--width: export.onnx_export.MAX_INPUT_SIDE (that module loads torch)


@dataclass(frozen=True)
class BenchConfig:
    models: Tuple[str, ...]
    threads: int
    scaling: bool
    out: Path
    prepare: PrepareConfig
    speed: SpeedConfig
    peak_seconds: float
    torch: bool
    profile: bool = False


def build_parser() -> argparse.ArgumentParser:
    # the [bench] extra brings [export] (the zoo is exported with torch) and matplotlib for report.png
    p = CliParser(prog="edge-bench", description=__doc__.split("\n\n")[0], extra="bench",
                  extra_modules=("torch", "onnx", "onnxscript", "tqdm", "matplotlib"),
                  formatter_class=argparse.RawDescriptionHelpFormatter,
                  epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("--models", help=f"comma-separated (default {','.join(DEFAULT_MODELS)}; "
                                    f"also adabins-80, adabins-256: 78 M parameters, slow; and the peers "
                                    f"{', '.join(PEERS)}: Depth Anything V2 Small, random weights, needs transformers)")
    p.add_argument("--threads", type=int, default=2, help="threads per backend (the drone has 2 cores)")
    p.add_argument("--quick", action="store_true", help="few iterations, one small model by default")
    p.add_argument("--scaling", action="store_true", help="also time 1 thread and report the speed-up")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder for report.{json,csv,png}")
    p.add_argument("--cache", type=Path, help="folder for exported/quantized models (default OUT/cache)")
    p.add_argument("--calib", type=Path, help="scene to calibrate INT8 on (default: synthetic frames)")
    p.add_argument("--calib-frames", type=int, default=4, help="INT8 calibration frames (default 4: speed only)")
    p.add_argument("--eval-frames", type=int, default=2, help="held-out frames for the INT8 agreement (default 2)")
    p.add_argument("--checkpoint", action="append", default=[], metavar="MODEL=PATH",
                   help="trained weights for one model (repeatable), e.g. safeuav-small=run/best.pth")
    p.add_argument("--height", type=int, help="override the paper's input height (all models)")
    p.add_argument("--width", type=int, help="override the paper's input width (all models)")
    p.add_argument("--iterations", type=int, help="timed iterations per backend (default 30, quick 3)")
    p.add_argument("--warmup", type=int, help="warm-up runs per backend (default 3, quick 1)")
    p.add_argument("--max-seconds", type=float, help="time budget per model (default 120, quick 20)")
    p.add_argument("--profile", action="store_true", help="add ONNX Runtime's per-op kernel time (FP32, INT8)")
    p.add_argument("--no-torch", action="store_true", help="leave out the PyTorch eager column")
    p.add_argument("--rebuild", action="store_true", help="re-export and re-quantize even if cached")
    p.add_no_progress()
    return p


def parse_config(argv: Optional[Sequence[str]]) -> BenchConfig:
    a = build_parser().parse_args(argv)
    check_threads("--threads", a.threads)
    for flag, value, least, most in (("--iterations", a.iterations, 1, None), ("--warmup", a.warmup, 0, None),
                                     ("--calib-frames", a.calib_frames, 1, None),
                                     ("--eval-frames", a.eval_frames, 1, None), ("--height", a.height, 16, MAX_SIDE),
                                     ("--width", a.width, 16, MAX_SIDE)):
        if value is not None:
            check_number(flag, value, least, most)
    if a.max_seconds is not None:
        check_number("--max-seconds", a.max_seconds, 0.0, lo_open=True, unit="seconds")
    if a.calib is not None:
        # fail now (missing folder, no rgb/, too few frames) rather than after exporting, or never on a cache hit
        frames = len(Scene(a.calib))
        if frames <= a.calib_frames:
            raise InputError(f"--calib {a.calib}: the scene has {frames} frame(s); --calib-frames {a.calib_frames} "
                             f"needs at least {a.calib_frames + 1} (the rest are held out for the INT8 agreement): "
                             f"lower --calib-frames or give a longer scene")
    if a.models is not None:
        names = tuple(n.strip() for n in a.models.split(",") if n.strip())
        if not names:
            raise InputError(f"--models '{a.models}' names no model; expected a comma-separated list such as "
                             f"{','.join(DEFAULT_MODELS)} (or leave --models out for that default)")
    else:
        names = QUICK_MODELS if a.quick else DEFAULT_MODELS
    lookup(names)
    speed = SpeedConfig(warmup=a.warmup if a.warmup is not None else (1 if a.quick else 3),
                        iterations=a.iterations if a.iterations is not None else (3 if a.quick else 30),
                        max_seconds=a.max_seconds if a.max_seconds is not None else (20.0 if a.quick else 120.0),
                        min_iterations=2 if a.quick else 5, progress=not a.no_progress)
    checkpoints = []
    for item in a.checkpoint:
        name, sep, path = item.partition("=")
        if not sep or name not in names:
            raise InputError(f"--checkpoint {item}: expected MODEL=PATH with MODEL one of {', '.join(names)}")
        if Path(path).is_dir():
            raise InputError(f"--checkpoint {item}: {path} is a folder, expected a checkpoint file")
        if not Path(path).is_file():
            raise InputError(f"--checkpoint {item}: {path} does not exist")
        checkpoints.append((name, Path(path)))
    prep = PrepareConfig(cache_dir=a.cache or a.out / "cache", height=a.height, width=a.width, calib_scene=a.calib,
                         calib_frames=a.calib_frames, eval_frames=a.eval_frames, rebuild=a.rebuild,
                         progress=not a.no_progress, checkpoints=tuple(checkpoints))
    return BenchConfig(names, a.threads, a.scaling, a.out, prep, speed, 0.3 if a.quick else 1.5, not a.no_torch,
                       a.profile)


def machine_info() -> dict:
    import onnxruntime

    from edge_landing.runtime.core.cpu_features import cpu_features

    isa = cpu_features()
    return {"cpu": isa.model, "logical_cpus": os.cpu_count(), "isa": isa.to_json(), "isa_summary": isa.summary(),
            "avx2": isa.has("AVX2"), "avx512_vnni": isa.has("AVX512_VNNI") or isa.has("AVX_VNNI"),
            "int8_dot_product": isa.int8_dot_product, "machine": platform.machine(),
            "onnxruntime": onnxruntime.__version__, "load_average_start": list(os.getloadavg())}


def openvino_usable(prepared, threads: int) -> Tuple[Dict[str, Tuple[Path, Optional[str]]], List[str]]:
    """OpenVINO's backend kinds, each with its file and precision, that compiled and ran in a child process, and
    a note per file that did not. Float layers run in f32, as edge-run runs them; on a CPU where OpenVINO would
    otherwise pick bf16 its default is timed too, as a peer: edge-run does not run it (bf16 changes the outputs
    behind the accuracy gate's back)."""
    from edge_landing.runtime.perception.backend import RUN_PRECISION, openvino_default_precision
    from edge_landing.runtime.perception.openvino_check import runs_in_child

    candidates: List[Tuple[str, str, Path, Optional[str]]] = [
        ("openvino", "FP32", prepared.fp32_path, RUN_PRECISION), ("openvino-int8", "INT8", prepared.int8_path, RUN_PRECISION)]
    default = openvino_default_precision()
    if default != RUN_PRECISION:
        candidates.append(("openvino-default", f"FP32 file at its default {default}", prepared.fp32_path, None))
    files: Dict[str, Tuple[Path, Optional[str]]] = {}
    notes: List[str] = []
    for kind, label, path, precision in candidates:
        ok, why = runs_in_child(path, threads, precision=precision)
        if ok:
            files[kind] = (path, precision)
        else:
            notes.append(f"OpenVINO {label} not timed: {why}")
    if "openvino-default" in files:
        notes.append(f"OpenVINO default: OpenVINO's own {default} for float layers on this CPU, a peer only "
                     f"(edge-run compiles in {RUN_PRECISION}: {default} changes the outputs and no accuracy gate checked it)")
    return files, notes


def bench_model(prepared, config: BenchConfig, peak_gflops: float) -> rep.BenchRow:
    from .flops import count_macs
    from .peak import matmul_backend, matmul_flop
    from .speed import (
        interleaved,
        openvino_available,
        openvino_backend,
        ort_backend,
        torch_backend,
    )

    m, c = prepared.model, prepared.contract
    counts = sorted({1, config.threads}) if config.scaling else [config.threads]
    # The same two ONNX files on OpenVINO's CPU runtime, each first compiled and run in a child process: a file
    # OpenVINO crashes on would take the whole run, and every model timed before it, down with it.
    openvino_files, notes = openvino_usable(prepared, config.threads) if openvino_available() else ({}, [])
    backends = []
    for t in counts:
        backends.append(ort_backend(prepared.fp32_path, c, t, "ort-fp32"))
        backends.append(ort_backend(prepared.int8_path, c, t, "ort-int8"))
        if config.torch:
            backends.append(torch_backend(prepared.module, c, t))
        for kind, (path, precision) in openvino_files.items():
            backends.append(openvino_backend(path, c, t, kind=kind, precision=precision))
    backends.append(matmul_backend(config.threads))
    timings = interleaved(backends, config.speed, desc=f"timing {m.name}")
    probe = timings.pop(f"matmul-peak@{config.threads}")
    peak_same_run = matmul_flop() / min(probe.latencies_s) / 1e9   # best run: closest to what the core can do
    main = {t.kind: t.to_json() for t in timings.values() if t.threads == config.threads}
    scaling = {}
    if config.scaling and len(counts) > 1:
        for kind in main:
            ips = {str(t.threads): t.images_per_s for t in timings.values() if t.kind == kind}
            scaling[kind] = {**ips, "speedup": ips[str(counts[-1])] / ips[str(counts[0])]}
    macs = count_macs(prepared.fp32_path)
    notes += ["random weights (speed only)"] if prepared.contract.source.get("weights") == "random" else []
    if m.peer_note:
        notes.append(m.peer_note)
    if macs.uncounted:
        notes.append(f"{len(macs.uncounted)} compute node(s) without inferred shapes left out of the MAC count")
    row = rep.BenchRow(model=m.name, arch=m.arch, task=m.task.value, input_hw=[c.input.height, c.input.width],
                       threads=config.threads, params_m=prepared.params / 1e6,
                       onnx_fp32_mb=prepared.fp32_path.stat().st_size / 1e6,
                       onnx_int8_mb=prepared.int8_path.stat().st_size / 1e6, gmac=macs.total / 1e9,
                       paper_v100_images_per_s=m.paper_v100_images_per_s, timings=main,
                       int8_agreement=prepared.int8_agreement, scaling=scaling, notes=notes,
                       peak_gflops_same_run=peak_same_run, paper_model_mb=m.paper_size_mb)
    if config.profile:
        from .profile import profile_ops

        row.profile = {kind: [o.to_json() for o in profile_ops(path, c, config.threads)]
                       for kind, path in (("ort-fp32", prepared.fp32_path), ("ort-int8", prepared.int8_path))}
    return row.finish(peak_gflops)


def run(config: BenchConfig) -> dict:
    """Prepare every model, probe the peak, time the models; returns the report dict (schema in report.py)."""
    from tqdm import tqdm

    from .peak import PeakConfig, measure_peak

    models = lookup(config.models)
    prepared = [prepare(m, config.prepare) for m in tqdm(models, desc="export + quantize", unit="model",
                                                         disable=not config.speed.progress)]
    info = machine_info()
    peak_cfg = PeakConfig(threads=config.threads, seconds=config.peak_seconds)
    peak_before = measure_peak(peak_cfg)
    rows = [bench_model(p, config, peak_before.gflops) for p in prepared]
    peak_after = measure_peak(peak_cfg)
    peak = max((peak_before, peak_after), key=lambda p: p.gflops)
    best = max([peak.gflops] + [r.peak_gflops_same_run or 0.0 for r in rows])
    rows = [r.finish(best) for r in rows]   # conservative: the share of the best matmul seen in the session
    info["load_average_end"] = list(os.getloadavg())
    notes = [f"share of peak = mean FP32 GFLOP/s / the best 1024² matmul seen in the session (stand-alone probes "
             f"{peak_before.gflops:.1f} before and {peak_after.gflops:.1f} after, and one inside each model's "
             f"round-robin); load average {info['load_average_start'][0]:.2f} -> {info['load_average_end'][0]:.2f}",
             "ORT sessions run with idle-thread spinning off so that the round-robin backends do not steal cores "
             "from each other"]
    if info["int8_dot_product"]:
        notes.append("this CPU has an int8 dot-product instruction (VNNI/AMX/ARM dot-product), the drone's may not: "
                     "INT8 gains here can exceed the drone's")
    else:
        notes.append("this CPU has no int8 dot-product instruction: ONNX Runtime's INT8 kernels widen to int16 here")
    report = {"schema": rep.SCHEMA_VERSION, "created_unix_s": time.time(), "machine": info,
            "peak": {**peak.to_json(), "gflops": best, "before": peak_before.to_json(), "after": peak_after.to_json()},
            "settings": {"threads": config.threads, "scaling": config.scaling, "warmup": config.speed.warmup,
                         "iterations": config.speed.iterations, "max_seconds_per_model": config.speed.max_seconds,
                         "models": list(config.models)},
            "notes": notes, "rows": [rep.row_to_json(r) for r in rows]}
    report["goals"] = [g.to_json() for g in check_goals(report)]
    return report


def check_sizes(config: BenchConfig) -> None:
    """Every model's input size must suit its network (--height/--width apply to all): refused before the
    first export rather than after the models before it were exported."""
    from edge_landing.export.onnx_export import check_input_size
    from edge_landing.export.zoo import get_arch

    from .catalog import input_hw

    for m in lookup(config.models):
        spec = get_arch(m.arch)
        h, w = input_hw(m, config.prepare)
        try:
            check_input_size(spec, h, w)
            spec.contract(m.task, h, w, **dict(m.options))
        except InputError as exc:
            raise InputError(f"--models {m.name} at {h}x{w} (--height/--width): {exc}") from None


def _main(argv: Optional[Sequence[str]] = None) -> int:
    config = parse_config(argv)
    check_sizes(config)
    # Idle OpenMP threads of PyTorch would otherwise spin and slow the next backend (before torch loads).
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    output_folder(config.out, "the --out folder")
    output_folder(config.prepare.cache_dir, "the --cache folder")
    report = run(config)
    print(rep.to_markdown(report))
    paths = [rep.write_json(report, config.out / "report.json"), rep.write_csv(report, config.out / "report.csv"),
             rep.write_png(report, config.out / "report.png")]
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
