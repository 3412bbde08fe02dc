"""Which runtime runs the model here: ONNX Runtime or OpenVINO, on the FP32 file or its INT8 twin (ARCHITECTURE.md §9).

After ``precision.pick_model`` has chosen among the files for ONNX Runtime, ``--runtime auto`` (the default) also
times OpenVINO's CPU plugin on the same candidate files when openvino is installed, and runs the fastest. Without
openvino nothing changes. OpenVINO runs the file with its own kernels (an INT8 QDQ file as its own int8
graph), so the accuracy gate that edge-quantize passed with ONNX Runtime is not assumed to carry over: an
OpenVINO candidate must first agree with ONNX Runtime on the same file (decoded depth within 5 % on 98 % of the
pixels, HVO labels on 98 %), on a structured test image. Before that, each file is compiled and run once by
OpenVINO in a child process (``openvino_check``): a file OpenVINO crashes on is refused, not run here. Timings
and agreement are cached like the precision probe, keyed by the files, the CPU, both runtimes' versions and the
threads.

    choice = pick_runtime(pick_model(path, Precision.AUTO), path, Precision.AUTO, RuntimeRequest.AUTO)
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Dict, List, Tuple

import cv2
import numpy as np

from edge_landing.runtime.core.cpu_features import cpu_features
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.perception.backend import Runtime, RuntimeRequest, openvino_available, runtime_version
from edge_landing.runtime.perception.inference import OnnxModel, SessionConfig, file_sha256
from edge_landing.runtime.perception.openvino_check import runs_in_child
from edge_landing.runtime.perception.precision import (
    ModelChoice,
    Precision,
    ProbeConfig,
    cache_dir,
    int8_twin,
    interleaved_p50_s,
    probe_input,
    quantization_of,
    read_cached_json,
    write_cache,
)

RUNTIME_CACHE_VERSION = 2        # 2: OpenVINO candidates that crashed in the child check have p50 null
MIN_AGREEMENT = 0.98          # share of pixels: depth within DEPTH_TOLERANCE, and the same HVO label
DEPTH_TOLERANCE = 0.05


@dataclass(frozen=True)
class Candidate:
    path: Path
    precision: Precision
    runtime: Runtime

    @property
    def label(self) -> str:
        return f"{self.runtime.value} {self.precision.value}"


def probe_image(height: int, width: int, seed: int = 0) -> np.ndarray:
    """A structured RGB test image: a bright band above a textured ground with blobs (random noise would put a
    network far from anything it was made for, where two runtimes' rounding can disagree without meaning)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((height, width, 3), np.float32)
    img[: height // 4] = (170, 190, 220)
    ground = rng.uniform(60, 160, (max(height // 8, 1), max(width // 8, 1), 3)).astype(np.float32)
    img[height // 4:] = cv2.resize(ground, (width, height - height // 4), interpolation=cv2.INTER_CUBIC)
    for _ in range(12):
        centre = (int(rng.integers(0, width)), int(rng.integers(height // 4, height)))
        cv2.circle(img, centre, int(rng.integers(2, max(3, width // 10))), tuple(float(c) for c in rng.uniform(0, 255, 3)), -1)
    return np.clip(img, 0, 255).astype(np.uint8)


def agreement(path: Path, threads: int) -> Tuple[bool, str]:
    """Whether OpenVINO and ONNX Runtime give the same outputs for ``path`` (and the figures)."""
    ort = OnnxModel.load(path, threads)
    ov = OnnxModel.load(path, config=SessionConfig(threads=threads, runtime=Runtime.OPENVINO))
    rgb = probe_image(*ort.input_hw)
    (d_a, h_a), (d_b, h_b) = (m.decode(m.run(m.prepare(rgb))) for m in (ort, ov))
    figures, ok = [], True
    if d_a is not None and d_b is not None:
        with np.errstate(invalid="ignore", divide="ignore"):
            share = float(np.mean(np.abs(d_b - d_a) <= DEPTH_TOLERANCE * np.abs(d_a)))
        figures.append(f"depth within {DEPTH_TOLERANCE:.0%} on {share:.1%}")
        ok &= share >= MIN_AGREEMENT
    if h_a is not None and h_b is not None:
        share = float(np.mean(h_a.argmax(axis=2) == h_b.argmax(axis=2)))
        figures.append(f"HVO labels agree on {share:.1%}")
        ok &= share >= MIN_AGREEMENT
    return ok, ", ".join(figures)


def _runner(c: Candidate, threads: int) -> Callable[[], object]:
    model = OnnxModel.load(c.path, config=SessionConfig(threads=threads, runtime=c.runtime))
    feed = {model.contract.input.name: probe_input(model.contract)}
    session = model.session
    return lambda: session.run(None, feed)


def measure(candidates: List[Candidate], config: ProbeConfig) -> Tuple[Dict[str, float], Dict[str, Any], str]:
    """p50 seconds per candidate label, OpenVINO agreement per label ([ok, figures]), and 'probed now' / 'cached'."""
    cpu = cpu_features()
    runtimes = sorted({c.runtime for c in candidates}, key=lambda r: r.value)
    files = "-".join(file_sha256(c.path)[:12] for c in candidates if c.runtime is runtimes[0])
    key = f"{files}-{cpu.key()}-{'-'.join(runtime_version(r) for r in runtimes)}-t{config.threads}"
    path = cache_dir(config) / f"runtime-{key}.json"
    hit = read_cached_json(path)
    labels = [c.label for c in candidates]
    if (hit is not None and hit.get("version") == RUNTIME_CACHE_VERSION
            and isinstance(hit.get("p50_s"), dict) and set(hit["p50_s"]) == set(labels)):
        p50 = {k: math.inf if v is None else float(v) for k, v in hit["p50_s"].items()}
        return p50, dict(hit.get("agrees", {})), f"cached in {path.parent}"
    agrees: Dict[str, Any] = {}
    crashed = set()
    for c in candidates:
        if c.runtime is Runtime.OPENVINO:
            runs, why = runs_in_child(c.path, config.threads)
            agrees[c.label] = list(agreement(c.path, config.threads)) if runs else [False, why]
            if not runs:
                crashed.add(c.label)
    timed = [c for c in candidates if c.label not in crashed]
    p50 = {c.label: math.inf for c in candidates}
    if timed:
        p50.update(zip([c.label for c in timed], interleaved_p50_s([_runner(c, config.threads) for c in timed],
                                                                   config)))
    record = {"version": RUNTIME_CACHE_VERSION, "agrees": agrees, "threads": config.threads,
              "p50_s": {k: v if math.isfinite(v) else None for k, v in p50.items()},
              "cpu": cpu.to_json(), "files": {c.label: str(c.path) for c in candidates}, "measured_unix_s": time.time()}
    saved = write_cache(path, record)
    return p50, agrees, "probed now" + (f", cached in {path.parent}" if saved else " (cache folder not writable)")


def _files(choice: ModelChoice, fp32_path: Path, precision: Precision) -> List[Tuple[Path, Precision]]:
    """The files the runtime choice may use: both FP32 and its gate-passing twin under ``auto`` precision."""
    if precision is not Precision.AUTO or quantization_of(fp32_path) is not None:
        return [(choice.path, choice.precision)]
    twin, _ = int8_twin(fp32_path)
    return [(fp32_path, Precision.FP32)] + ([(twin, Precision.INT8)] if twin is not None else [])


def pick_runtime(choice: ModelChoice, fp32_path: Path, precision: Precision, request: RuntimeRequest,
                 config: ProbeConfig = ProbeConfig()) -> ModelChoice:
    """``choice`` (ONNX Runtime's file) or a faster OpenVINO candidate; raises InputError when openvino is asked
    for and not installed, or disagrees with ONNX Runtime on every file."""
    if request is RuntimeRequest.ONNXRUNTIME or (request is RuntimeRequest.AUTO and not openvino_available()):
        return choice
    if request is RuntimeRequest.OPENVINO and not openvino_available():
        raise InputError("--runtime openvino: openvino is not installed (pip install 'edge-landing[openvino]')")
    runtimes = [Runtime.OPENVINO] if request is RuntimeRequest.OPENVINO else [Runtime.ONNXRUNTIME, Runtime.OPENVINO]
    candidates = [Candidate(p, prec, r) for r in runtimes for p, prec in _files(choice, fp32_path, precision)]
    p50, agrees, how = measure(candidates, config)
    usable = [c for c in candidates if c.runtime is not Runtime.OPENVINO or agrees.get(c.label, [False])[0]]
    if not usable:
        raise InputError(f"--runtime openvino with {fp32_path.name}: OpenVINO's outputs differ from ONNX Runtime's, "
                         f"or it cannot run the file ({'; '.join(f'{k}: {v[1]}' for k, v in agrees.items())})")
    best = min(usable, key=lambda c: p50[c.label])
    timed = ", ".join(f"{c.label} {p50[c.label] * 1e3:.1f}" if math.isfinite(p50[c.label]) else f"{c.label} not run"
                      for c in candidates)
    refused = [f"{k} refused: {v[1]}" for k, v in agrees.items() if not v[0]]
    why = (f"fastest here (p50 ms: {timed}; {' '.join(cpu_features().features) or 'this CPU'}, "
           f"{config.threads} thread(s); {how})" + (f"; {'; '.join(refused)}" if refused else ""))
    if best.runtime is Runtime.ONNXRUNTIME and best.path == choice.path:
        return replace(choice, reason=f"{choice.reason}; ONNX Runtime is the {why}")   # the precision's own reason
    return replace(choice, path=best.path, precision=best.precision, runtime=best.runtime, reason=why)
