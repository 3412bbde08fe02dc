"""Inference driven only by the model contract (ARCHITECTURE.md §5), on ONNX Runtime or OpenVINO.

The backend sits behind two methods, ``prepare`` (RGB uint8 image -> input tensor) and ``run`` (tensor ->
raw outputs); ``decode`` turns raw outputs into metric depth and HVO probabilities. ``predict`` does all
three for one frame. Example::

    model = OnnxModel.load("model.onnx", threads=2)
    pred = model.predict(rgb_uint8)            # Prediction with depth_m (H×W) and/or hvo_prob (H×W×3)
"""
from __future__ import annotations

import hashlib
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

import cv2
import numpy as np

from edge_landing.runtime.core.errors import ContractError, InputError
from edge_landing.runtime.core.messages import Prediction
from edge_landing.runtime.perception.backend import OpenVinoSession, Runtime
from edge_landing.runtime.perception.contract import Layout, ModelContract
from edge_landing.runtime.perception.input_fit import InputFit


@dataclass(frozen=True)
class SessionConfig:
    """How to run a model: threads (the drone has 2 cores), graph optimisation, execution providers."""

    threads: int = 2
    providers: Tuple[str, ...] = ("CPUExecutionProvider",)
    # ONNX Runtime's worker threads spin after each run by default. On 2 cores that steals the CPU from
    # whatever runs next: fusion in the pipeline, or the second model of a depth + HVO pair.
    spin: bool = False
    runtime: Runtime = Runtime.ONNXRUNTIME   # OpenVINO's CPU plugin runs the same file (perception/backend.py)


def file_sha256(path: os.PathLike[str] | str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def read_contract(path: os.PathLike[str] | str) -> ModelContract:
    """Read and validate the contract of an ONNX file."""
    sess = _open_session(Path(path), SessionConfig(threads=1))
    return ModelContract.from_metadata(sess.get_modelmeta().custom_metadata_map, where=str(path))


def _open_session(path: Path, config: SessionConfig) -> Any:
    """An ``onnxruntime.InferenceSession`` (onnxruntime ships no type information, hence Any)."""
    import onnxruntime as ort

    if not path.is_file():
        what = "is a folder, not a file" if path.is_dir() else "does not exist"
        raise ContractError(f"model file {path} {what} (expected an .onnx file)")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = config.threads
    opts.inter_op_num_threads = 1
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3
    if not config.spin:
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    try:
        return ort.InferenceSession(str(path), sess_options=opts, providers=list(config.providers))
    except Exception as exc:  # onnxruntime raises its own untyped errors for unreadable files
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ContractError(f"{path} is not a loadable ONNX model ({first[:200]})") from None


class OnnxModel:
    """One session (ONNX Runtime's, or OpenVINO's behind the same calls) plus its contract."""

    def __init__(self, session: Any, contract: ModelContract, path: Path) -> None:
        self.session = session
        self.contract = contract
        self.path = path
        self.sha256 = file_sha256(path)
        self._check_io()

    @staticmethod
    def load(path: os.PathLike[str] | str, threads: int = 2, config: Optional[SessionConfig] = None) -> OnnxModel:
        config = config or SessionConfig(threads=threads)
        path = Path(path)
        if config.runtime is Runtime.OPENVINO:
            contract = read_contract(path)    # the contract lives in the ONNX metadata, read with ONNX Runtime
            return OnnxModel(OpenVinoSession(path, config.threads), contract, path)
        session = _open_session(path, config)
        contract = ModelContract.from_metadata(session.get_modelmeta().custom_metadata_map, where=str(path))
        return OnnxModel(session, contract, path)

    def _check_io(self) -> None:
        c = self.contract
        inputs = {i.name: i for i in self.session.get_inputs()}
        if c.input.name not in inputs:
            raise ContractError(f"{self.path}: edge.input names '{c.input.name}' but the graph's inputs are "
                                f"{sorted(inputs)}")
        shape = inputs[c.input.name].shape
        expected = ([1, 3, c.input.height, c.input.width] if c.input.layout is Layout.NCHW
                    else [1, c.input.height, c.input.width, 3])
        fixed = [d for d in shape if isinstance(d, int)]
        if len(shape) != 4 or (len(fixed) == 4 and list(shape) != expected):
            raise ContractError(f"{self.path}: input '{c.input.name}' has shape {shape}; the contract says {expected}")
        outputs = {o.name for o in self.session.get_outputs()}
        for spec, key in ((c.depth, "edge.depth"), (c.hvo, "edge.hvo")):
            if spec is not None and spec.output not in outputs:
                raise ContractError(f"{self.path}: {key} names output '{spec.output}' but the graph's outputs are "
                                    f"{sorted(outputs)}")

    @property
    def input_hw(self) -> Tuple[int, int]:
        return self.contract.input.height, self.contract.input.width

    # -- the two-method backend interface -------------------------------------------------------------
    def prepare(self, rgb: np.ndarray) -> np.ndarray:
        """RGB uint8 H×W×3 of any size -> the network input tensor (float32, batch 1)."""
        return preprocess(rgb, self.contract)

    def run(self, tensor: np.ndarray) -> Dict[str, np.ndarray]:
        names = [s.output for s in (self.contract.depth, self.contract.hvo) if s is not None]
        values = self.session.run(names, {self.contract.input.name: tensor})
        return dict(zip(names, values))

    # -- decoding -------------------------------------------------------------------------------------
    @property
    def output_stride(self) -> int:
        """Input size / output size of the depth head (1 without one)."""
        return self.contract.depth.stride if self.contract.depth is not None else 1

    def fit(self, frame_hw: Tuple[int, int]) -> InputFit:
        """Where a frame of ``frame_hw`` sits in this model's input (letterboxed unless it is 4:3 like the input)."""
        return InputFit.for_frame(int(frame_hw[0]), int(frame_hw[1]), *self.input_hw)

    def decode(self, outputs: Dict[str, np.ndarray], out_hw: Optional[Tuple[int, int]] = None,
               scale: float = 1.0, fit: Optional[InputFit] = None) -> Tuple[Optional[np.ndarray], Optional[np.ndarray]]:
        """Raw outputs -> (depth_m H×W, hvo_prob H×W×3) of the image part given by ``fit`` (default: all of the
        output), at ``out_hw`` (default: the output's own resolution)."""
        return decode_outputs(outputs, self.contract, out_hw, scale, fit)

    def predict(self, rgb: np.ndarray, frame_id: int = 0, capture_time_s: float = 0.0,
                out_hw: Optional[Tuple[int, int]] = None, scale: float = 1.0) -> Prediction:
        """One frame end to end. Raises InputError for a malformed image (entry points check first)."""
        t0 = time.perf_counter()
        tensor = self.prepare(rgb)
        t1 = time.perf_counter()
        outputs = self.run(tensor)
        t2 = time.perf_counter()
        depth, hvo = self.decode(outputs, out_hw, scale, self.fit(rgb.shape[:2]))
        t3 = time.perf_counter()
        valid, reason = True, ""
        if depth is not None and not np.isfinite(depth).any():
            valid, reason = False, "depth output has no finite value"
        if hvo is not None and not np.isfinite(hvo).all():
            valid, reason = False, "HVO output is not finite"
        return Prediction(frame_id, capture_time_s, depth, hvo, valid, reason, scale,
                          {"preprocess": t1 - t0, "inference": t2 - t1, "decode": t3 - t2})


def check_image(rgb: np.ndarray) -> None:
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        desc = f"{rgb.dtype} array of shape {rgb.shape}" if isinstance(rgb, np.ndarray) else type(rgb).__name__
        raise InputError(f"expected an RGB uint8 image of shape H×W×3, got a {desc}")
    if rgb.shape[0] < 8 or rgb.shape[1] < 8:
        raise InputError(f"image of {rgb.shape[0]}x{rgb.shape[1]} pixels is too small (at least 8x8 expected)")


def preprocess(rgb: np.ndarray, contract: ModelContract) -> np.ndarray:
    """Fit into the model's fixed size (resized, letterboxed when not of the input's aspect: input_fit.InputFit),
    x = (rgb*scale - mean)/std, in the contract's layout and colour order."""
    check_image(rgb)
    spec = contract.input
    if rgb.shape[:2] != (spec.height, spec.width):
        rgb = InputFit.for_frame(rgb.shape[0], rgb.shape[1], spec.height, spec.width).place(rgb)
    # (rgb*scale - mean)/std folded into one multiply-add per channel, written straight into the output layout:
    # this runs on every frame, and the naive chain of whole-image temporaries cost ~1.5 ms at 240x320.
    gain = np.float32(spec.scale) / np.asarray(spec.std, np.float32)
    offset = -np.asarray(spec.mean, np.float32) / np.asarray(spec.std, np.float32)
    order = (2, 1, 0) if spec.color == "BGR" else (0, 1, 2)
    h, w = rgb.shape[:2]
    if spec.layout is Layout.NCHW:
        x = np.empty((1, 3, h, w), np.float32)
        for out_c, in_c in enumerate(order):
            np.multiply(rgb[..., in_c], gain[out_c], out=x[0, out_c], casting="unsafe")
            x[0, out_c] += offset[out_c]
        return x
    x = (rgb[..., ::-1] if spec.color == "BGR" else rgb).astype(np.float32)
    # OpenCV applies a per-channel scalar in one pass; numpy's broadcast over a last axis of 3 is 2-3x slower.
    # A 4-tuple is a cv::Scalar at runtime; OpenCV's stubs only list Mat operands here.
    cv2.multiply(x, (*map(float, gain), 0.0), dst=x)  # type: ignore[call-overload]
    cv2.add(x, (*map(float, offset), 0.0), dst=x)  # type: ignore[call-overload]
    return x[None]


def _single_map(y: np.ndarray, layout: Layout, name: str) -> np.ndarray:
    """Squeeze a 1-channel output (N1HW / NHW1 / NHW) to H×W."""
    y = np.asarray(y)
    if y.ndim == 4:
        y = y[0, 0] if layout is Layout.NCHW else y[0, ..., 0]
    elif y.ndim == 3:
        y = y[0]
    if y.ndim != 2:
        raise ContractError(f"output '{name}' has shape {np.shape(y)}; expected one depth channel")
    return y


def decode_outputs(outputs: Dict[str, np.ndarray], contract: ModelContract, out_hw: Optional[Tuple[int, int]] = None,
                   scale: float = 1.0, fit: Optional[InputFit] = None) -> Tuple[Optional[np.ndarray], Optional[np.ndarray]]:
    """Metric depth and HVO probabilities of the image part (``fit``; default all of it), at ``out_hw``."""
    depth = hvo = None
    if contract.depth is not None:
        y = _single_map(outputs[contract.depth.output], contract.depth.layout, contract.depth.output)
        if fit is not None:
            y = fit.crop(y)
        depth = contract.depth.to_metres(y)
        if out_hw is not None and depth.shape != tuple(out_hw):
            depth = cv2.resize(depth, (out_hw[1], out_hw[0]), interpolation=cv2.INTER_LINEAR)
        if scale != 1.0:
            depth = depth * np.float32(scale)
    if contract.hvo is not None:
        logits = np.asarray(outputs[contract.hvo.output])[0]
        if contract.hvo.layout is Layout.NCHW:
            logits = logits.transpose(1, 2, 0)
        if logits.ndim != 3 or logits.shape[2] != 3:
            raise ContractError(f"HVO output '{contract.hvo.output}' decodes to shape {logits.shape}; expected H×W×3")
        logits = logits.astype(np.float32)
        if fit is not None:
            logits = fit.crop(logits)
        if out_hw is not None and logits.shape[:2] != tuple(out_hw):
            logits = cv2.resize(logits, (out_hw[1], out_hw[0]), interpolation=cv2.INTER_LINEAR)
        e = np.exp(logits - logits.max(axis=2, keepdims=True))
        hvo = e / e.sum(axis=2, keepdims=True)
    return depth, hvo
