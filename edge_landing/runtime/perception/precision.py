"""Which model file runs on this CPU: FP32 or its INT8 twin, whichever is faster here (ARCHITECTURE.md §9).

INT8 is not faster everywhere: with VNNI it is ~1.6-1.9x FP32, on an AVX2-only CPU it can be slower (0.68x
for SafeUAV-Net-Small). So ``auto`` times both files on first use, on this machine, with the runtime's own
session settings: a short interleaved probe (warm-up, then alternating runs with the order rotating), and
caches the verdict under ``~/.cache/edge-landing`` keyed by both files' SHA-256, the CPU's features and the
ONNX Runtime version, so the next start is instant. Only an INT8 file that passed edge-quantize's accuracy
gate and was quantized from this very FP32 file (its recorded ``fp32_sha256``) is a candidate. Example::

    choice = pick_model(Path("edgenet.onnx"), Precision.AUTO)
    print(choice.line())    # "edgenet.int8.onnx (int8): 1.71x FP32 on this CPU (p50 3.9 vs 6.7 ms, ...)"
"""
from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np

from edge_landing.runtime.core.choices import ChoiceEnum
from edge_landing.runtime.core.cpu_features import CpuFeatures, cpu_features
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.perception.backend import Runtime
from edge_landing.runtime.perception.contract import Layout, ModelContract
from edge_landing.runtime.perception.inference import SessionConfig, _open_session, file_sha256

CACHE_ENV = "EDGE_LANDING_CACHE"     # overrides the cache folder (tests point it at a temporary one)
CACHE_VERSION = 1


class Precision(ChoiceEnum):
    AUTO = "auto"    # the faster of FP32 and a gate-passing INT8 twin, probed on this CPU
    FP32 = "fp32"
    INT8 = "int8"

    @classmethod
    def _label(cls) -> str:
        return "--precision"


@dataclass(frozen=True)
class ProbeConfig:
    threads: int = 2
    warmup: int = 3          # runs per file before timing (first runs allocate and pick kernels)
    iterations: int = 15     # timed runs per file, interleaved
    max_seconds: float = 6.0  # stop timing early (after 5 rounds) on a slow model: first use must stay short
    cache_dir: Optional[Path] = None   # default: $EDGE_LANDING_CACHE, else $XDG_CACHE_HOME or ~/.cache, /edge-landing


@dataclass(frozen=True)
class ModelChoice:
    path: Path
    precision: Precision          # FP32 or INT8: what ``path`` is
    reason: str
    runtime: Runtime = Runtime.ONNXRUNTIME   # what runs it (perception/runtime_choice.py)

    def line(self) -> str:
        on = "" if self.runtime is Runtime.ONNXRUNTIME else f" on {self.runtime.value}"
        return f"model {self.path.name} ({self.precision.value}){on}: {self.reason}"


def cache_dir(config: ProbeConfig) -> Path:
    if config.cache_dir is not None:
        return config.cache_dir
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "edge-landing"


def _metadata(path: Path) -> Dict[str, str]:
    meta: Dict[str, str] = _open_session(path, SessionConfig(threads=1)).get_modelmeta().custom_metadata_map
    return meta


def quantization_of(path: Path) -> Optional[Dict[str, Any]]:
    """The file's ``edge.quantization`` record (None for an FP32 file)."""
    raw = _metadata(path).get("edge.quantization")
    if raw is None:
        return None
    value = json.loads(raw)
    return value if isinstance(value, dict) else None


def same_export(fp32_path: Path, int8_path: Path) -> bool:
    """The INT8 file carries the FP32 file's contract and its dated ``edge.source`` (which may since have gained
    notes: the shipped FP32 got its provenance after quantization, so its SHA-256 no longer matches)."""
    a, b = _metadata(fp32_path), _metadata(int8_path)
    if any(a.get(k) != b.get(k) for k in ("edge.arch", "edge.task", "edge.input", "edge.depth", "edge.hvo")):
        return False
    try:
        src_a, src_b = json.loads(a.get("edge.source", "{}")), json.loads(b.get("edge.source", "{}"))
    except ValueError:
        return False
    # the export's date (edge-export writes it) is what identifies it; without one, the contract alone is not enough
    return (isinstance(src_a, dict) and isinstance(src_b, dict) and bool(src_b.get("date"))
            and all(src_a.get(k) == v for k, v in src_b.items()))


def int8_twin(fp32_path: Path) -> Tuple[Optional[Path], str]:
    """The INT8 file quantized from ``fp32_path`` (``X.int8.onnx`` beside ``X.onnx``) if it passed the
    accuracy gate; otherwise None and why not."""
    twin = fp32_path.with_name(fp32_path.name[: -len(".onnx")] + ".int8.onnx") if fp32_path.name.endswith(
        ".onnx") else fp32_path.with_name(fp32_path.name + ".int8.onnx")
    if not twin.is_file():
        return None, f"no INT8 file {twin.name} beside it"
    q = quantization_of(twin)
    if q is None:
        return None, f"{twin.name} is not an edge-quantize output"
    if q.get("passed") is not True:
        return None, f"{twin.name} failed the accuracy gate"
    recorded = q.get("fp32_sha256")
    if recorded != file_sha256(fp32_path) and not same_export(fp32_path, twin):
        return None, f"{twin.name} was quantized from another FP32 file"
    return twin, ""


def probe_input(contract: ModelContract, seed: int = 0) -> np.ndarray:
    """A random normalised input in the contract's layout (speed does not depend on the values)."""
    spec = contract.input
    shape = (1, 3, spec.height, spec.width) if spec.layout is Layout.NCHW else (1, spec.height, spec.width, 3)
    return np.random.default_rng(seed).uniform(-2.0, 2.0, shape).astype(np.float32)


def interleaved_p50_s(runs: List[Callable[[], object]], config: ProbeConfig) -> List[float]:
    """Median latency of each callable: warm-up, then rounds in which each runs once, the first rotating,
    so that every one sees the same machine load (the ratio is what counts)."""
    for _ in range(config.warmup):
        for run in runs:
            run()
    lat: List[List[float]] = [[] for _ in runs]
    end = time.perf_counter() + config.max_seconds
    for i in range(config.iterations):
        for j in range(len(runs)):
            k = (i + j) % len(runs)
            t0 = time.perf_counter()
            runs[k]()
            lat[k].append(time.perf_counter() - t0)
        if i >= 4 and time.perf_counter() > end:
            break
    return [float(np.median(x)) for x in lat]


def probe(fp32_path: Path, int8_path: Path, config: ProbeConfig) -> Tuple[float, float]:
    """p50 seconds of (FP32, INT8) on this machine with the runtime's session settings."""
    from edge_landing.runtime.perception.inference import OnnxModel

    def runner(path: Path) -> Callable[[], object]:
        model = OnnxModel.load(path, threads=config.threads)
        feed = {model.contract.input.name: probe_input(model.contract)}
        session = model.session
        return lambda: session.run(None, feed)

    runs = [runner(fp32_path), runner(int8_path)]
    fp32_s, int8_s = interleaved_p50_s(runs, config)
    return fp32_s, int8_s


def cache_key(fp32_sha: str, int8_sha: str, cpu: CpuFeatures, threads: int) -> str:
    import onnxruntime

    return f"{fp32_sha[:16]}-{int8_sha[:16]}-{cpu.key()}-ort{onnxruntime.__version__}-t{threads}"


def read_cached_json(path: Path) -> Optional[Dict[str, Any]]:
    """A cached JSON object, or None when missing or unreadable (then the probe runs again)."""
    try:
        value = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return value if isinstance(value, dict) else None


def _read_cache(path: Path) -> Optional[Dict[str, Any]]:
    value = read_cached_json(path)
    ok = (value is not None and value.get("version") == CACHE_VERSION
          and isinstance(value.get("fp32_p50_s"), float) and isinstance(value.get("int8_p50_s"), float))
    return value if ok else None


def write_cache(path: Path, record: Dict[str, Any]) -> bool:
    """Atomic write; a read-only home only costs a probe on every start (returns False)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".probe-", dir=path.parent)
        with os.fdopen(fd, "w") as fh:
            json.dump(record, fh, indent=1, sort_keys=True)
        os.replace(tmp, path)
        return True
    except OSError:
        return False


def measured(fp32_path: Path, int8_path: Path, config: ProbeConfig) -> Tuple[float, float, str]:
    """(FP32 p50 s, INT8 p50 s, 'cached' / 'probed now') for this pair on this CPU."""
    cpu = cpu_features()
    key = cache_key(file_sha256(fp32_path), file_sha256(int8_path), cpu, config.threads)
    path = cache_dir(config) / f"precision-{key}.json"
    hit = _read_cache(path)
    if hit is not None:
        return float(hit["fp32_p50_s"]), float(hit["int8_p50_s"]), f"cached in {path.parent}"
    fp32_s, int8_s = probe(fp32_path, int8_path, config)
    record = {"version": CACHE_VERSION, "fp32": str(fp32_path), "int8": str(int8_path), "fp32_p50_s": fp32_s,
              "int8_p50_s": int8_s, "threads": config.threads, "cpu": cpu.to_json(), "measured_unix_s": time.time()}
    saved = write_cache(path, record)
    return fp32_s, int8_s, "probed now" + (f", cached in {path.parent}" if saved else " (cache folder not writable)")


def pick_model(path: Path, precision: Precision, config: ProbeConfig = ProbeConfig()) -> ModelChoice:
    """The file to run for ``path`` (an FP32 model, or an INT8 one given on purpose) at ``precision``.

    Raises InputError when ``int8`` is asked for and there is no gate-passing INT8 twin (entry points turn
    that into one line, exit 2). An INT8 file given directly is used as it is, whatever ``precision`` says.
    """
    if quantization_of(path) is not None:
        if precision is Precision.FP32:
            raise InputError(f"--precision fp32 with {path.name}, which is an INT8 model; give its FP32 file")
        return ModelChoice(path, Precision.INT8, "given as an INT8 file")
    if precision is Precision.FP32:
        return ModelChoice(path, Precision.FP32, "asked for (--precision fp32)")
    twin, why_not = int8_twin(path)
    if twin is None:
        if precision is Precision.INT8:
            raise InputError(f"--precision int8 with {path}: {why_not}")
        return ModelChoice(path, Precision.FP32, f"{why_not}, so FP32")
    if precision is Precision.INT8:
        return ModelChoice(twin, Precision.INT8, "asked for (--precision int8 / --int8)")
    fp32_s, int8_s, how = measured(path, twin, config)
    ratio = fp32_s / int8_s if int8_s > 0 else float("inf")
    cpu = cpu_features()
    detail = (f"p50 INT8 {int8_s * 1e3:.1f} ms vs FP32 {fp32_s * 1e3:.1f} ms at {config.threads} thread(s) on "
              f"{' '.join(cpu.features) or 'this CPU'}; {how}")
    if int8_s < fp32_s:
        return ModelChoice(twin, Precision.INT8, f"{ratio:.2f}x FP32 on this CPU ({detail})")
    return ModelChoice(path, Precision.FP32, f"INT8 is not faster on this CPU ({ratio:.2f}x; {detail})")
