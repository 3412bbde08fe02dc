"""The machine's practical FP32 peak, probed with large square matmuls at a given thread count.

Two probes: ONNX Runtime's MatMul (thread count set per session, the same kernels the models use) and
numpy's BLAS in a child process (OpenBLAS reads its thread count only at start-up, so the child gets
``OPENBLAS_NUM_THREADS``). The peak is the better of the two; both are reported. Example::

    peak = measure_peak(threads=2)
    print(peak.gflops, peak.ort_gflops, peak.numpy_gflops)
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass

import numpy as np

_NUMPY_PROBE = r"""
import json, sys, time
import numpy as np
n, seconds = int(sys.argv[1]), float(sys.argv[2])
a = np.random.default_rng(0).standard_normal((n, n), dtype=np.float32)
b = np.random.default_rng(1).standard_normal((n, n), dtype=np.float32)
a @ b
best, t_end = float("inf"), time.perf_counter() + seconds
while time.perf_counter() < t_end:
    t0 = time.perf_counter(); a @ b; best = min(best, time.perf_counter() - t0)
print(json.dumps({"gflops": 2.0 * n ** 3 / best / 1e9}))
"""


@dataclass(frozen=True)
class PeakConfig:
    threads: int = 2
    size: int = 1024
    seconds: float = 1.5      # per probe; the best (shortest) run counts, to see through other load


@dataclass(frozen=True)
class Peak:
    threads: int
    ort_gflops: float
    numpy_gflops: float

    @property
    def gflops(self) -> float:
        return max(v for v in (self.ort_gflops, self.numpy_gflops) if np.isfinite(v))

    def to_json(self) -> dict:
        return {"threads": self.threads, "gflops": self.gflops, "ort_gflops": self.ort_gflops,
                "numpy_gflops": self.numpy_gflops}


def _matmul_model(n: int):
    from onnx import TensorProto, helper, numpy_helper

    b = numpy_helper.from_array(np.random.default_rng(1).standard_normal((n, n)).astype(np.float32), "b")
    graph = helper.make_graph([helper.make_node("MatMul", ["a", "b"], ["c"])], "peak",
                              [helper.make_tensor_value_info("a", TensorProto.FLOAT, [n, n])],
                              [helper.make_tensor_value_info("c", TensorProto.FLOAT, [n, n])], [b])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    return model


def _matmul_session(size: int, threads: int):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    sess = ort.InferenceSession(_matmul_model(size).SerializeToString(), opts, providers=["CPUExecutionProvider"])
    return sess, np.random.default_rng(0).standard_normal((size, size)).astype(np.float32)


def matmul_flop(size: int = PeakConfig.size) -> float:
    return 2.0 * size ** 3


def matmul_backend(threads: int, size: int = PeakConfig.size):
    """The matmul probe as one more backend of the round-robin, so that a model's share of the peak is a
    ratio from the same run (same load) like the others: GFLOP/s = images_per_s × matmul_flop / 1e9."""
    from .speed import Backend

    sess, a = _matmul_session(size, threads)
    return Backend(f"matmul-peak@{threads}", "matmul-peak", threads, lambda: sess.run(None, {"a": a}))


def ort_matmul_gflops(config: PeakConfig) -> float:
    sess, a = _matmul_session(config.size, config.threads)
    sess.run(None, {"a": a})
    best, t_end = float("inf"), time.perf_counter() + config.seconds
    while time.perf_counter() < t_end:
        t0 = time.perf_counter()
        sess.run(None, {"a": a})
        best = min(best, time.perf_counter() - t0)
    return 2.0 * config.size ** 3 / best / 1e9


def numpy_matmul_gflops(config: PeakConfig) -> float:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": str(config.threads), "OMP_NUM_THREADS": str(config.threads),
           "MKL_NUM_THREADS": str(config.threads)}
    try:
        out = subprocess.run([sys.executable, "-c", _NUMPY_PROBE, str(config.size), str(config.seconds)],
                             env=env, capture_output=True, text=True, timeout=60 + 4 * config.seconds, check=True)
        return float(json.loads(out.stdout.strip().splitlines()[-1])["gflops"])
    except (subprocess.SubprocessError, ValueError, KeyError, IndexError):
        return float("nan")  # the ORT probe alone still gives a peak


def measure_peak(config: PeakConfig = PeakConfig()) -> Peak:
    return Peak(config.threads, ort_matmul_gflops(config), numpy_matmul_gflops(config))
