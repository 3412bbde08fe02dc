"""Static INT8 quantization with an accuracy guard (ARCHITECTURE.md §9).

ONNX Runtime's static QDQ quantizer with the settings that pay off on an x86 CPU without VNNI: uint8
activations, int8 weights, per-channel with ``reduce_range``, ``quant_pre_process`` first. Calibration
frames come from a scene folder and go through the runtime's own preprocessing (``OnnxModel.prepare``);
the frames after the first ``calib_frames`` are held out and used to compare INT8 with FP32. The model
contract is carried over and the settings and the comparison are added under ``edge.quantization``.
Example::

    report = quantize("m.onnx", "m.int8.onnx", QuantizeConfig(calib_scene=Path("scene"), calib_frames=16))
    if not report.passed:
        print(report.reasons)          # the INT8 file was not written (unless config.force)
"""
from __future__ import annotations

import logging
import os
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import List, Optional, Tuple, Union

import numpy as np

from edge_landing.evaluation.scene import Scene
from edge_landing.runtime.core.choices import ChoiceEnum
from edge_landing.runtime.core.cpu_features import cpu_features
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.perception.inference import OnnxModel

from .calib_frames import SceneCalibrationReader, split_frames
from .quant_check import FrameRef, Tolerance, check_tolerance, compare, frame_label
from .quant_speed import SearchConfig, SpeedSearch, search_float_branches

log = logging.getLogger(__name__)

# Ops whose output is the "head": the walk back from the depth output stops after the first one on each path.
_COMPUTE_OPS = ("Conv", "ConvTranspose", "Gemm", "MatMul")
_HEAD_WALK_LIMIT = 24  # nodes; a head is a handful of nodes, this only guards against eating the graph


class CalibrationMethod(ChoiceEnum):
    MINMAX = "minmax"
    ENTROPY = "entropy"
    PERCENTILE = "percentile"


class QuantFormat(ChoiceEnum):
    """QDQ: Q/DQ pairs that ONNX Runtime fuses into int8 kernels; QOperator: QLinearConv etc. in the file."""

    QDQ = "qdq"
    QOPERATOR = "qoperator"


class QuantKind(ChoiceEnum):
    """8-bit integer type of activations or weights."""

    U8 = "u8"
    S8 = "s8"


_ORT_TYPE_NAME = {QuantKind.U8: "QUInt8", QuantKind.S8: "QInt8"}


class DepthHead(ChoiceEnum):
    """Whether the last conv(s) feeding the depth output stay float: ``auto`` = float for depth models."""

    AUTO = "auto"
    FLOAT = "float"
    INT8 = "int8"


# ONNX Runtime's CPU provider has no int8 ConvTranspose kernel: a quantized one runs as DQ -> float -> Q and is
# slower than leaving it float (SafeUAV-Net-Small: 78 ms vs 49 ms for its three, same run).
DEFAULT_FLOAT_OP_TYPES = ("ConvTranspose",)
# Per-architecture op types kept float by default. AdaBins: the depth is a softmax-weighted sum of bin centres
# that the mViT's MatMul/Gemm regress from one token; an error there shifts every bin of every pixel at once.
ARCH_FLOAT_OP_TYPES = {"adabins": DEFAULT_FLOAT_OP_TYPES + ("MatMul", "Gemm")}


def float_op_types_for(arch: str) -> Tuple[str, ...]:
    return ARCH_FLOAT_OP_TYPES.get(arch, DEFAULT_FLOAT_OP_TYPES)


@dataclass(frozen=True)
class QuantizeConfig:
    calib_scene: Union[Path, Tuple[Path, ...]]   # one scene folder or several (frames shared out evenly)
    calib_frames: int = 16               # in all (over all scenes)
    eval_frames: int = 16                # held-out frames compared (after each scene's calibration frames)
    per_channel: bool = True
    reduce_range: bool = True
    quant_format: QuantFormat = QuantFormat.QDQ
    activation_type: QuantKind = QuantKind.U8
    weight_type: QuantKind = QuantKind.S8
    method: CalibrationMethod = CalibrationMethod.MINMAX
    depth_head: DepthHead = DepthHead.AUTO
    exclude_nodes: Tuple[str, ...] = ()
    float_op_types: Optional[Tuple[str, ...]] = None   # op types left float; None = the architecture's default
    subpixel: bool = True                # rewrite strided ConvTranspose as Conv + DepthToSpace (export/subpixel.py)
    tolerance: Tolerance = Tolerance()
    force: bool = False                  # write the INT8 file even when it fails the tolerance
    threads: int = 2
    progress: bool = True
    # Time INT8 against FP32 on this machine (interleaved, after warm-up) and record it with the CPU's
    # features: INT8 that passes the accuracy gate can still be slower than FP32 on a CPU without VNNI.
    speed_gate: bool = True
    speed_iterations: int = 30
    # Leave in float the branches that are slower in INT8 here (export/quant_speed.py); auto = only when full
    # INT8 is under 1.3x FP32 on this CPU. Needs speed_gate.
    speed_search: SpeedSearch = SpeedSearch.AUTO

    @property
    def calib_scenes(self) -> Tuple[Path, ...]:
        if isinstance(self.calib_scene, (str, Path)):
            return (Path(self.calib_scene),)
        return tuple(Path(p) for p in self.calib_scene)


@dataclass
class QuantReport:
    input: Path
    output: Path
    written: bool
    passed: bool
    reasons: List[str]
    settings: dict
    comparison: dict
    size_fp32_mb: float
    size_int8_mb: float = float("nan")


def depth_head_nodes(model, depth_output: str) -> List[str]:
    """Names of the nodes of the depth head, kept in float.

    With other outputs (a joint depth + HVO net): every node that feeds the depth output and no other output,
    i.e. the whole depth branch after the shared trunk (quantizing its 3×3 conv made EdgeNet's per-pixel depth
    too noisy for the fusion's flatness test: 0 of 200 frames with a target, 139 with it in float).
    A depth-only net: from the output back to (and including) the first compute op on each path.
    """
    producers = {out: node for node in model.graph.node for out in node.output}
    others = [o.name for o in model.graph.output if o.name != depth_output]
    if others:
        shared = set(_ancestors(producers, others))
        return [n for n in _ancestors(producers, [depth_output]) if n not in shared]
    return _ancestors(producers, [depth_output], stop_at_compute=True, limit=_HEAD_WALK_LIMIT)


def _ancestors(producers: dict, outputs: List[str], stop_at_compute: bool = False,
               limit: Optional[int] = None) -> List[str]:
    """Names of the nodes the given graph outputs depend on (nearest first); with ``stop_at_compute`` a path
    ends at its first compute op (Conv, Gemm, ...), which is still included."""
    found: List[str] = []
    stack, seen = list(outputs), set()
    while stack and (limit is None or len(found) < limit):
        node = producers.get(stack.pop())
        if node is None or node.name in seen:
            continue
        seen.add(node.name)
        found.append(node.name)
        if not (stop_at_compute and node.op_type in _COMPUTE_OPS):
            stack.extend(node.input)
    return found


def _name_nodes(model) -> None:
    """The quantizer's exclusion list works by node name; give unnamed nodes stable unique names."""
    used = {n.name for n in model.graph.node if n.name}
    for i, node in enumerate(model.graph.node):
        if not node.name:
            name = f"{node.op_type}_{i}"
            while name in used:
                name += "_"
            node.name = name
            used.add(name)


def _pre_process(src: Path, dst: Path) -> None:
    from onnxruntime.quantization.shape_inference import quant_pre_process

    # Symbolic shape inference fails on some exported graphs; ONNX's own inference is enough for conv nets.
    attempts: tuple[dict[str, bool], ...] = (
        {}, {"skip_symbolic_shape": True}, {"skip_symbolic_shape": True, "skip_optimization": True})
    last = None
    for kwargs in attempts:
        try:
            quant_pre_process(str(src), str(dst), **kwargs)
            return
        except Exception as exc:  # the pre-processor raises assorted untyped errors
            last = exc
            log.info("quant_pre_process %s failed (%s); retrying with fewer steps", kwargs, str(exc)[:120])
    raise InputError(f"{src}: ONNX Runtime's quant_pre_process failed ({str(last)[:200]})")


def _subpixel(model, fp32: OnnxModel, rgb: np.ndarray) -> int:
    """Rewrite ConvTranspose nodes in place so they quantize (export/subpixel.py); the rewrite is exact, and
    checked on one frame against the FP32 model so that a bug can never reach the INT8 file."""
    import onnx
    import onnxruntime as ort

    from .subpixel import rewrite_conv_transposes

    candidate = onnx.ModelProto()
    candidate.CopyFrom(model)
    count = rewrite_conv_transposes(candidate)
    if count == 0:
        return 0
    x = fp32.prepare(rgb)
    ref = fp32.session.run(None, {fp32.contract.input.name: x})
    names = [o.name for o in fp32.session.get_outputs()]
    sess = ort.InferenceSession(candidate.SerializeToString(), providers=["CPUExecutionProvider"])
    got = sess.run(names, {fp32.contract.input.name: x})
    for name, a, b in zip(names, ref, got):
        scale = float(np.max(np.abs(a))) or 1.0
        if a.shape != b.shape or float(np.max(np.abs(a - b))) > 1e-4 * scale:
            log.warning("sub-pixel rewrite changed output %s; keeping ConvTranspose", name)
            return 0
    model.CopyFrom(candidate)
    return count


def _settings(config: QuantizeConfig, calib: List[FrameRef], excluded: List[str], float_head: bool, fp32: OnnxModel,
              float_ops: Tuple[str, ...]) -> dict:
    import onnxruntime

    return {"format": "QDQ" if config.quant_format is QuantFormat.QDQ else "QOperator",
            "activations": _ORT_TYPE_NAME[config.activation_type], "weights": _ORT_TYPE_NAME[config.weight_type],
            "per_channel": config.per_channel,
            "reduce_range": config.reduce_range, "method": config.method.value, "float_depth_head": float_head,
            "excluded_nodes": excluded, "float_op_types": list(float_ops),
            "calibration": {"scenes": [str(p) for p in config.calib_scenes], "frames": len(calib),
                            "first": frame_label(calib[0]), "last": frame_label(calib[-1])},
            "fp32_sha256": fp32.sha256, "onnxruntime": onnxruntime.__version__, "tolerance": asdict(config.tolerance),
            "tuned_on_cpu": cpu_features().to_json()}


def speed_check(fp32_path: Path, int8_path: Path, config: QuantizeConfig) -> dict:
    """INT8 against FP32 on this CPU: p50 latency of each, timed interleaved (the edge-run probe's method with
    more rounds), at ``config.threads``."""
    from edge_landing.runtime.perception.precision import ProbeConfig, probe

    fp32_s, int8_s = probe(fp32_path, int8_path, ProbeConfig(threads=config.threads, warmup=5,
                                                             iterations=config.speed_iterations, max_seconds=60.0))
    return {"threads": config.threads, "fp32_p50_ms": fp32_s * 1e3, "int8_p50_ms": int8_s * 1e3,
            "int8_vs_fp32": fp32_s / int8_s, "faster_here": int8_s < fp32_s, "cpu": cpu_features().summary()}


class _QuantizerLogFilter(logging.Filter):
    """ONNX Runtime's quantizer logs INFO lines to the root logger, one per weight channel whose scale it
    raises for the int32 bias (thousands for big models); count those and let warnings through."""

    def __init__(self):
        super().__init__()
        self.raised_scales = 0

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno > logging.INFO:
            return True
        if "Increased scale" in str(record.msg):
            self.raised_scales += 1
        return False


def _run_quantizer(src: Path, dst: Path, reader: SceneCalibrationReader, config: QuantizeConfig,
                   excluded: List[str], float_ops: Tuple[str, ...]) -> int:
    """Run ONNX Runtime's static quantizer; returns how many weight channels had their scale raised so that
    the int32 bias fits (each such channel loses weight precision: a hint when the tolerance trips)."""
    from onnxruntime.quantization import CalibrationMethod as OrtMethod
    from onnxruntime.quantization import QuantFormat as OrtFormat
    from onnxruntime.quantization import QuantType, quantize_static
    from onnxruntime.quantization.registry import QDQRegistry, QLinearOpsRegistry

    op_types = sorted((set(QLinearOpsRegistry) | set(QDQRegistry)) - set(float_ops))
    method = {CalibrationMethod.MINMAX: OrtMethod.MinMax, CalibrationMethod.ENTROPY: OrtMethod.Entropy,
              CalibrationMethod.PERCENTILE: OrtMethod.Percentile}[config.method]
    quiet = _QuantizerLogFilter()
    logging.getLogger().addFilter(quiet)
    try:
        # Not CalibMaxIntermediateOutputs: in this ONNX Runtime it drops the collected chunk instead of merging it.
        kind = {QuantKind.U8: QuantType.QUInt8, QuantKind.S8: QuantType.QInt8}
        fmt = OrtFormat.QDQ if config.quant_format is QuantFormat.QDQ else OrtFormat.QOperator
        quantize_static(str(src), str(dst), reader, quant_format=fmt, per_channel=config.per_channel,
                        reduce_range=config.reduce_range, activation_type=kind[config.activation_type],
                        weight_type=kind[config.weight_type], nodes_to_exclude=excluded, calibrate_method=method,
                        op_types_to_quantize=op_types)
    finally:
        logging.getLogger().removeFilter(quiet)
    if quiet.raised_scales:
        log.info("ONNX Runtime raised the scale of %d weight channel(s) so that their int32 bias fits",
                 quiet.raised_scales)
    return quiet.raised_scales


def _write_metadata(path: Path, fp32: OnnxModel, settings: dict) -> None:
    """Every metadata entry of the FP32 file (the contract and anything else), plus edge.quantization."""
    import onnx

    model = onnx.load(str(path))
    props = {**fp32.session.get_modelmeta().custom_metadata_map,
             **fp32.contract.with_quantization(settings).to_metadata()}
    del model.metadata_props[:]
    for key, value in props.items():
        model.metadata_props.add(key=key, value=value)
    onnx.save(model, str(path))


def quantize(input: os.PathLike | str, output: os.PathLike | str, config: QuantizeConfig) -> QuantReport:  # noqa: A002
    """Quantize ``input`` to ``output`` and check it on held-out frames.

    Returns the report; the INT8 file is written only when it passes the tolerance or ``config.force``
    is set (a failing model is never left at ``output`` otherwise). The FP32 file is never touched.
    """
    import onnx

    src, dst = Path(input), Path(output)
    if dst.resolve() == src.resolve():
        raise InputError(f"--out {dst} is the FP32 input itself; choose another file (e.g. model.int8.onnx)")
    if not dst.parent.is_dir():
        raise InputError(f"output folder {dst.parent} does not exist")
    fp32 = OnnxModel.load(src, threads=config.threads)
    if fp32.contract.quantization is not None:
        raise InputError(f"{src} is already quantized (edge.quantization is set); quantize the FP32 model")
    calib, held_out = split_frames([Scene(p) for p in config.calib_scenes], config.calib_frames, config.eval_frames)
    float_head = (config.depth_head is DepthHead.FLOAT
                  or (config.depth_head is DepthHead.AUTO and fp32.contract.depth is not None))
    if float_head and fp32.contract.depth is None:
        raise InputError(f"{src} has no depth head (edge.task '{fp32.contract.task}'); drop --keep-depth-head-float")

    with tempfile.TemporaryDirectory(prefix=".edge-quantize-", dir=dst.parent) as tmp:
        pre, out_tmp = Path(tmp) / "pre.onnx", Path(tmp) / "int8.onnx"
        _pre_process(src, pre)
        model = onnx.load(str(pre))
        rewritten = _subpixel(model, fp32, calib[0][0].read_rgb(calib[0][1])) if config.subpixel else 0
        _name_nodes(model)
        onnx.save(model, str(pre))
        names = {n.name for n in model.graph.node}
        unknown = [n for n in config.exclude_nodes if n not in names]
        if unknown:
            raise InputError(f"--exclude-node {unknown[0]} is not a node of {src} after pre-processing")
        op_types = {n.op_type for n in model.graph.node}
        missing = [t for t in config.float_op_types or () if t not in op_types]
        if missing:
            raise InputError(f"--float-op-type {missing[0]}: {src} has no node of that type "
                             f"(its op types: {', '.join(sorted(op_types))})")
        excluded = list(config.exclude_nodes)
        if float_head and fp32.contract.depth is not None:     # (checked above: float_head implies a depth head)
            excluded += [n for n in depth_head_nodes(model, fp32.contract.depth.output) if n not in excluded]
        del model
        float_ops = (config.float_op_types if config.float_op_types is not None
                     else float_op_types_for(fp32.contract.arch))

        def build(extra: List[str], path: Path) -> int:
            reader = SceneCalibrationReader(calib, fp32.prepare, fp32.contract.input.name, config.progress)
            raised = _run_quantizer(pre, path, reader, config, excluded + extra, float_ops)
            _write_metadata(path, fp32, {"search_candidate": True})   # the contract, so that it loads
            return raised

        raised = build([], out_tmp)
        search: dict = {}
        if config.speed_gate and config.speed_search is not SpeedSearch.NEVER:
            search_cfg = SearchConfig(config.speed_search, threads=config.threads)
            out_tmp, kept_float, search = search_float_branches(src, pre, out_tmp, excluded, build, search_cfg)
            excluded += kept_float
        settings = {**_settings(config, calib, excluded, float_head, fp32, float_ops),
                    "subpixel_conv_transposes": rewritten, "weight_channels_scaled_for_bias": raised}
        if search:
            settings["speed_search"] = search
        _write_metadata(out_tmp, fp32, settings)
        comparison = compare(fp32, OnnxModel.load(out_tmp, threads=config.threads), held_out,
                             config.progress)
        reasons = check_tolerance(comparison, config.tolerance)
        passed = not reasons
        settings = {**settings, "comparison": comparison, "passed": passed, "forced": bool(reasons) and config.force}
        if config.speed_gate:
            settings["speed"] = speed_check(src, out_tmp, config)
        _write_metadata(out_tmp, fp32, settings)
        report = QuantReport(src, dst, written=False, passed=passed, reasons=reasons, settings=settings,
                             comparison=comparison, size_fp32_mb=src.stat().st_size / 1e6,
                             size_int8_mb=out_tmp.stat().st_size / 1e6)
        if passed or config.force:
            os.replace(out_tmp, dst)  # atomic: a reader never sees half a model
            report.written = True
    return report
