"""The runtimes a model file can run on: ONNX Runtime (always), OpenVINO's CPU plugin (when installed).

Both run the same ONNX file; which is faster depends on the CPU and the file (measured on the project's AMD EPYC
with VNNI: OpenVINO ran EdgeNet's INT8 file ~1.5x faster than ONNX Runtime, and SafeUAV-Net-Small's FP32
file faster than either runtime's INT8). ``runtime_choice`` times them on the machine and picks.
:class:`OpenVinoSession` offers the calls ``OnnxModel`` makes of an ONNX Runtime session, so everything after
it (contract, preprocessing, decoding) is shared. The contract is still read from the file's ONNX metadata.
"""
from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import numpy as np

from edge_landing.runtime.core.choices import ChoiceEnum
from edge_landing.runtime.core.errors import ContractError, InputError


class Runtime(ChoiceEnum):
    ONNXRUNTIME = "onnxruntime"
    OPENVINO = "openvino"

    @classmethod
    def _label(cls) -> str:
        return "runtime"


class RuntimeRequest(ChoiceEnum):
    """What ``--runtime`` asks for: one runtime, or the faster here among those installed."""

    AUTO = "auto"
    ONNXRUNTIME = "onnxruntime"
    OPENVINO = "openvino"

    @classmethod
    def _label(cls) -> str:
        return "--runtime"


def openvino_available() -> bool:
    return importlib.util.find_spec("openvino") is not None


# OpenVINO's inference precision for float layers in edge-run (and in every timing that stands for edge-run).
RUN_PRECISION = "f32"


def openvino_default_precision() -> str:
    """The precision OpenVINO's CPU plugin runs float layers in when not told (``"bf16"`` on CPUs with native bf16)."""
    import openvino as ov

    return "bf16" if "BF16" in ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES") else "f32"


def runtime_version(runtime: Runtime) -> str:
    if runtime is Runtime.OPENVINO:
        import openvino

        return f"ov{openvino.__version__.split('-')[0]}"
    import onnxruntime

    return f"ort{onnxruntime.__version__}"


@dataclass(frozen=True)
class PortInfo:
    """Name and shape of a graph input or output (None for a dynamic dimension), as ONNX Runtime reports them."""

    name: str
    shape: List[Optional[int]]


class OpenVinoSession:
    """One OpenVINO CPU compiled model with one infer request (latency hint, one stream, ``threads`` threads).

    ``precision`` is OpenVINO's inference precision for float layers: ``"f32"`` (what edge-run runs), or None
    for OpenVINO's own default (bf16 on CPUs with native bf16; edge-bench times that as a peer only).
    """

    def __init__(self, path: Path | str, threads: int, precision: Optional[str] = RUN_PRECISION) -> None:
        if not openvino_available():
            raise InputError("--runtime openvino: openvino is not installed (pip install 'edge-landing[openvino]')")
        import openvino as ov

        try:
            # f32: on CPUs with bf16 support OpenVINO otherwise runs float layers in bf16, which changes the
            # outputs (depth off by >5 % on 2.3 % of EdgeNet's pixels here) behind the accuracy gate's back.
            config: Dict[str, Any] = {"INFERENCE_NUM_THREADS": threads, "PERFORMANCE_HINT": "LATENCY", "NUM_STREAMS": 1}
            if precision is not None:
                config["INFERENCE_PRECISION_HINT"] = precision
            self._compiled: Any = ov.Core().compile_model(str(path), "CPU", config)
        except Exception as exc:  # OpenVINO raises its own untyped errors
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise ContractError(f"{path}: OpenVINO cannot compile it ({first[:200]})") from None
        self._request: Any = self._compiled.create_infer_request()

    @staticmethod
    def _port(port: Any) -> PortInfo:
        dims = [d.get_length() if d.is_static else None for d in port.get_partial_shape()]
        return PortInfo(port.get_any_name(), dims)

    def get_inputs(self) -> List[PortInfo]:
        return [self._port(p) for p in self._compiled.inputs]

    def get_outputs(self) -> List[PortInfo]:
        return [self._port(p) for p in self._compiled.outputs]

    def run(self, names: Optional[Sequence[str]], feeds: Dict[str, np.ndarray]) -> List[np.ndarray]:
        """Like ``InferenceSession.run``. The arrays are copies: the request reuses its buffers on the next run."""
        result = self._request.infer(feeds)
        ports = [self._compiled.output(n) for n in names] if names else list(self._compiled.outputs)
        return [np.array(result[p], copy=True) for p in ports]
