"""Interleaved latency measurement of several backends of one model (ARCHITECTURE.md §9).

Every iteration runs each backend once, round-robin, with the starting backend rotating, so all of them see
the same machine load and their ratios come from one run even on a noisy shared machine. Example::

    backends = [ort_backend("m.onnx", threads=2), ort_backend("m.int8.onnx", threads=2, name="ort-int8")]
    timings = interleaved(backends, SpeedConfig(warmup=3, iterations=30))
    print(timings["ort-int8"].images_per_s)
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.perception.backend import RUN_PRECISION
from edge_landing.runtime.perception.contract import Layout, ModelContract


@dataclass(frozen=True)
class SpeedConfig:
    warmup: int = 3
    iterations: int = 30
    max_seconds: float = 120.0     # per model: stop early (after min_iterations) when exceeded
    min_iterations: int = 5
    progress: bool = True


@dataclass(frozen=True)
class Backend:
    """One way to run the model once on a fixed input; ``kind`` groups rows (ort-fp32, ort-int8, torch...)."""

    name: str
    kind: str
    threads: int
    run: Callable[[], object]
    before: Optional[Callable[[], None]] = None   # e.g. torch.set_num_threads, cheap, run before every call


@dataclass(frozen=True)
class Timing:
    name: str
    kind: str
    threads: int
    latencies_s: tuple

    @property
    def images_per_s(self) -> float:
        return len(self.latencies_s) / float(np.sum(self.latencies_s))

    def percentile_ms(self, q: float) -> float:
        return float(np.percentile(self.latencies_s, q) * 1e3)

    def to_json(self) -> dict:
        return {"name": self.name, "kind": self.kind, "threads": self.threads, "iterations": len(self.latencies_s),
                "images_per_s": self.images_per_s, "p50_ms": self.percentile_ms(50),
                "p90_ms": self.percentile_ms(90), "p99_ms": self.percentile_ms(99)}


def input_tensor(contract: ModelContract, seed: int = 0) -> np.ndarray:
    """A preprocessed-looking random input (values in the normalised range) in the contract's layout."""
    spec = contract.input
    rgb = np.random.default_rng(seed).integers(0, 256, (spec.height, spec.width, 3)).astype(np.float32)
    x = (rgb * spec.scale - np.asarray(spec.mean, np.float32)) / np.asarray(spec.std, np.float32)
    if spec.layout is Layout.NCHW:
        x = x.transpose(2, 0, 1)
    return np.ascontiguousarray(x[None], dtype=np.float32)


def ort_session(path: os.PathLike | str, threads: int):
    """An ONNX Runtime session as the drone runs it, except that idle threads do not spin: a spinning pool
    would steal the cores from the next backend in the round-robin and bias the ratios."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])


def ort_backend(path: os.PathLike | str, contract: ModelContract, threads: int, kind: str = "ort-fp32",
                name: Optional[str] = None) -> Backend:
    sess = ort_session(path, threads)
    feed = {contract.input.name: input_tensor(contract)}
    return Backend(name or f"{kind}@{threads}", kind, threads, lambda: sess.run(None, feed))


def torch_backend(module, contract: ModelContract, threads: int) -> Backend:
    """PyTorch eager (inference mode). torch's thread count is global, so it is set before every call."""
    import torch

    x = torch.from_numpy(input_tensor(contract))
    module = module.eval()

    def run():
        with torch.inference_mode():
            return module(x)

    return Backend(f"torch@{threads}", "torch", threads, run, before=lambda: torch.set_num_threads(threads))


def openvino_available() -> bool:
    import importlib.util

    return importlib.util.find_spec("openvino") is not None


def openvino_backend(path: os.PathLike | str, contract: ModelContract, threads: int, kind: str = "openvino",
                     name: Optional[str] = None, precision: Optional[str] = RUN_PRECISION) -> Backend:
    """OpenVINO's CPU plugin on the same ONNX file (an INT8 QDQ file runs as OpenVINO's own int8 kernels), compiled
    as edge-run compiles it (``runtime.perception.backend.OpenVinoSession``: float layers in f32 unless
    ``precision`` says otherwise; None is OpenVINO's own default). Idle threads do not spin here either
    (OpenVINO's TBB workers sleep between requests)."""
    from edge_landing.runtime.perception.backend import OpenVinoSession

    session = OpenVinoSession(os.fspath(path), threads, precision=precision)
    feed = {contract.input.name: input_tensor(contract)}
    return Backend(name or f"{kind}@{threads}", kind, threads, lambda: session.run(None, feed))


def interleaved(backends: Sequence[Backend], config: SpeedConfig = SpeedConfig(), desc: str = "timing"
                ) -> Dict[str, Timing]:
    """Warm up every backend, then time them round-robin; returns name -> Timing."""
    from tqdm import tqdm

    if not backends:
        raise InputError("nothing to time: no backend is available")
    names = [b.name for b in backends]
    if len(set(names)) != len(names):
        raise InputError(f"backend names must be unique, got {names}")
    for _ in range(config.warmup):
        for b in backends:
            if b.before:
                b.before()
            b.run()
    lat: Dict[str, List[float]] = {b.name: [] for b in backends}
    t_end = time.perf_counter() + config.max_seconds
    bar = tqdm(range(config.iterations), desc=desc, unit="it", disable=not config.progress, leave=False)
    for i in bar:
        for j in range(len(backends)):
            b = backends[(i + j) % len(backends)]   # rotate who goes first
            if b.before:
                b.before()
            t0 = time.perf_counter()
            b.run()
            lat[b.name].append(time.perf_counter() - t0)
        if i + 1 >= config.min_iterations and time.perf_counter() > t_end:
            break
    bar.close()
    return {b.name: Timing(b.name, b.kind, b.threads, tuple(lat[b.name])) for b in backends}
