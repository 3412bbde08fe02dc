"""PyTorch -> one self-describing ONNX file (ARCHITECTURE.md §5), verified against PyTorch before it is written.

    from edge_landing.export.zoo import get_arch
    from edge_landing.export.onnx_export import export_onnx
    report = export_onnx(get_arch("safeuav-small"), Task.HVO, "safeuav_small.onnx", 240, 320,
                         checkpoint="safeuav_small_hvo.pkl")
    print(report.max_rel_error)

Steps: build the network, load the authors' checkpoint (or keep random weights, loudly), export at a fixed
input size and opset ≤ 20 with the legacy exporter (the dynamo exporter is the fall-back), write the model
contract into ``metadata_props``, run ``onnx.checker``, then run ONNX Runtime through
``edge_landing.runtime.perception.inference.OnnxModel`` (which validates the contract) against PyTorch on random images.
The file is written to a temporary name and renamed only when everything agreed, so a failed export leaves
nothing behind.
"""
from __future__ import annotations

import logging
import math
import os
import sys
import time
import warnings
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Tuple

import numpy as np
import torch

from edge_landing.runtime.core.errors import EdgeError, InputError
from edge_landing.runtime.perception.contract import Layout, ModelContract, Task
from edge_landing.runtime.perception.inference import OnnxModel, SessionConfig

from .checkpoints import trusted_checkpoints
from .zoo.registry import ArchSpec

log = logging.getLogger(__name__)
MAX_OPSET = 20   # ONNX Runtime's static quantizer does not take newer opsets (ARCHITECTURE.md §9)
MAX_INPUT_SIDE = 4096   # pixels each way: larger is a typo (100000x100000 float32 would be 120 GB of input alone)


@dataclass(frozen=True)
class ExportSettings:
    """How to export and how strictly to verify.

    ``rel_tolerance``: largest accepted max|ort - torch| / max|torch| per output (float32 kernels differ a little).
    """

    opset: int = 17
    rel_tolerance: float = 1e-3
    checks: int = 2
    seed: int = 0
    threads: int = 1
    progress: bool = True
    trust_checkpoint: bool = False   # unpickle objects besides tensors (old checkpoints); runs code from the file


@dataclass(frozen=True)
class ExportReport:
    path: Path
    arch: str
    task: Task
    height: int
    width: int
    parameters: int
    source: dict
    output_shapes: Dict[str, Tuple[int, ...]]
    max_abs_error: float
    max_rel_error: float
    size_bytes: int
    seconds: float
    exporter: str = "torchscript"

    def summary(self) -> str:
        shapes = ", ".join(f"{k} {list(v)}" for k, v in self.output_shapes.items())
        return (f"wrote {self.path} ({self.size_bytes / 1e6:.1f} MB): {self.arch} {self.task} "
                f"{self.height}x{self.width}, {self.parameters:,} parameters, outputs {shapes}; "
                f"ONNX Runtime vs PyTorch max abs error {self.max_abs_error:.3g}, "
                f"max rel error {self.max_rel_error:.3g}; weights: {self.source.get('weights')}")


def check_input_size(spec: ArchSpec, height: int, width: int) -> None:
    """Fixed input sizes must suit the network's strides; anything else is one clear InputError."""
    m = spec.size_multiple
    if height % m or width % m:
        raise InputError(f"input size {height}x{width} does not suit {spec.name}: height and width must be "
                         f"multiples of {m} (default {spec.input_hw[0]}x{spec.input_hw[1]})")
    if height < spec.min_hw[0] or width < spec.min_hw[1]:
        raise InputError(f"input size {height}x{width} is too small for {spec.name}: at least "
                         f"{spec.min_hw[0]}x{spec.min_hw[1]} expected (default {spec.input_hw[0]}x{spec.input_hw[1]})")
    if max(height, width) > MAX_INPUT_SIDE:
        raise InputError(f"input size {height}x{width} is too large: at most {MAX_INPUT_SIDE} pixels each way "
                         f"(default {spec.input_hw[0]}x{spec.input_hw[1]})")


def option_problem(spec: ArchSpec, name: str, value: Any) -> Optional[str]:
    """What is wrong with one build option's value, or None. Every option of the zoo is a count (channels,
    bins) or a depth in metres, so finite and > 0; a count (its default is an int) takes whole numbers only."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        return f"must be a finite number > 0, got {value}"
    if isinstance(spec.options.get(name), int) and not float(value).is_integer():
        return f"must be a whole number, got {value}"
    return None


def check_options(spec: ArchSpec, options: Optional[Mapping]) -> dict:
    """Only the architecture's own options are accepted (e.g. --bins means nothing to SafeUAV)."""
    options = dict(options or {})
    unknown = sorted(k for k in options if k not in spec.options)
    if unknown:
        accepted = ", ".join(sorted(spec.options)) or "none"
        raise InputError(f"option(s) {', '.join(unknown)} do not apply to {spec.name} (it accepts: {accepted})")
    for name, value in options.items():
        problem = option_problem(spec, name, value)
        if problem:
            raise InputError(f"option {name} {problem}")
    merged = {**spec.options, **options}
    lo, hi = merged.get("min_depth"), merged.get("max_depth")
    if lo is not None and hi is not None and not 0 < float(lo) < float(hi):
        raise InputError(f"depth range must satisfy 0 < min_depth < max_depth, got {lo} and {hi}")
    return merged


def export_onnx(spec: ArchSpec, task: Optional[Task | str], out_path: os.PathLike | str, height: int, width: int,
                checkpoint: Optional[os.PathLike | str] = None, options: Optional[Mapping] = None,
                settings: ExportSettings = ExportSettings()) -> ExportReport:
    """Export one architecture to ``out_path``; raises EdgeError (and writes nothing) on any failure."""
    t0 = time.perf_counter()
    task = Task.from_string(str(task)) if task is not None else spec.default_task
    if task not in spec.tasks:
        raise InputError(f"{spec.name} has no '{task}' head; expected one of: {', '.join(map(str, spec.tasks))}")
    if not 7 <= settings.opset <= MAX_OPSET:
        raise InputError(f"opset {settings.opset} is not supported; expected 7..{MAX_OPSET}")
    check_input_size(spec, height, width)
    opts = check_options(spec, options)
    # Build the contract first: it validates architecture-specific size rules (e.g. AdaBins' patch count)
    # before seconds are spent building a large network.
    base_contract = spec.contract(task, height, width, **opts)
    out_path = Path(out_path)
    if checkpoint is not None and not Path(checkpoint).is_file():
        raise InputError(f"checkpoint {checkpoint} does not exist")
    if out_path.suffix != ".onnx":
        raise InputError(f"output {out_path} should end in .onnx")
    try:
        out_path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder {out_path.parent} for {out_path.name}: "
                         f"{exc.strerror}") from None
    if not os.access(out_path.parent, os.W_OK):
        raise InputError(f"output folder {out_path.parent} is not writable")
    tmp = out_path.with_name(f".{out_path.name}.{os.getpid()}.tmp")
    if checkpoint is None:
        _warn_random(spec.name)
    steps = _progress(settings.progress, total=5, desc=f"export {spec.name}")
    try:
        model = spec.build(task, **opts).eval()
        steps.update(1)
        with trusted_checkpoints(settings.trust_checkpoint):
            source = _load_weights(spec, model, checkpoint)
        steps.update(1)
        contract = replace(base_contract, source=source)
        x = torch.zeros(_input_shape(contract), dtype=torch.float32)
        names = tuple(spec.output_names(task))
        exporter = _torch_export(model, x, tmp, contract.input.name, names, settings.opset)
        steps.update(1)
        _write_contract(tmp, contract)
        steps.update(1)
        shapes, abs_err, rel_err = _verify(model, tmp, contract, names, settings)
        steps.update(1)
        os.replace(tmp, out_path)
    finally:
        steps.close()
        if tmp.exists():
            tmp.unlink()
    report = ExportReport(path=out_path, arch=spec.name, task=task, height=height, width=width,
                          parameters=sum(p.numel() for p in model.parameters()), source=source,
                          output_shapes=shapes, max_abs_error=abs_err, max_rel_error=rel_err,
                          size_bytes=out_path.stat().st_size, seconds=time.perf_counter() - t0, exporter=exporter)
    log.debug(report.summary())
    return report


def _load_weights(spec: ArchSpec, model: torch.nn.Module, checkpoint) -> dict:
    base = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "torch": torch.__version__}
    if checkpoint is not None:
        return {**base, **spec.load_checkpoint(model, Path(checkpoint))}
    return {**base, "weights": "random", "checkpoint": None,
            "note": "random initialisation, not trained: for speed tests and plumbing only"}


def _warn_random(arch: str) -> None:
    banner = "!" * 78
    print(f"{banner}\n!!! WARNING: no checkpoint given: exporting {arch} with RANDOM weights.\n"
          f"!!! Its outputs are meaningless; use it only for speed tests and plumbing.\n{banner}",
          file=sys.stderr)


def _input_shape(contract: ModelContract) -> Tuple[int, int, int, int]:
    h, w = contract.input.height, contract.input.width
    return (1, 3, h, w) if contract.input.layout is Layout.NCHW else (1, h, w, 3)


def _torch_export(model, x, path: Path, input_name: str, output_names, opset: int) -> str:
    """Legacy TorchScript exporter first (robust for these CNNs); the dynamo exporter if it fails."""
    kwargs: dict[str, Any] = dict(input_names=[input_name], output_names=list(output_names), opset_version=opset)
    errors = []
    for dynamo in (False, True):
        try:
            with warnings.catch_warnings(), torch.no_grad():
                warnings.simplefilter("ignore")
                if dynamo:
                    torch.onnx.export(model, (x,), str(path), dynamo=True, external_data=False, **kwargs)
                else:
                    torch.onnx.export(model, (x,), str(path), dynamo=False, do_constant_folding=True, **kwargs)
            return "dynamo" if dynamo else "torchscript"
        except Exception as exc:  # torch.onnx raises many unrelated types; report the first line of each
            errors.append(f"{'dynamo' if dynamo else 'torchscript'}: {_first_line(exc)}")
            log.warning("ONNX export with the %s exporter failed: %s", "dynamo" if dynamo else "torchscript",
                        _first_line(exc))
    raise EdgeError(f"torch.onnx.export failed with both exporters ({'; '.join(errors)})")


def _write_contract(path: Path, contract: ModelContract) -> None:
    import onnx

    model = onnx.load(str(path))
    if len(model.graph.input) != 1:
        raise EdgeError(f"exported graph has {len(model.graph.input)} inputs; expected exactly one")
    del model.metadata_props[:]
    for key, value in contract.to_metadata().items():
        model.metadata_props.add(key=key, value=value)
    try:
        onnx.checker.check_model(model)
    except onnx.checker.ValidationError as exc:
        raise EdgeError(f"exported model fails onnx.checker: {_first_line(exc)}") from None
    onnx.save(model, str(path))   # one file: every model of the zoo is far below protobuf's 2 GB


def _verify(model, path: Path, contract: ModelContract, names, settings: ExportSettings):
    """Run ONNX Runtime and PyTorch on the same random images; refuse if they disagree."""
    ort_model = OnnxModel.load(path, config=SessionConfig(threads=settings.threads))
    rng = np.random.default_rng(settings.seed)
    h, w = contract.input.height, contract.input.width
    max_abs, max_rel, shapes = 0.0, 0.0, {}
    for _ in range(settings.checks):
        rgb = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
        x = ort_model.prepare(rgb)      # the contract's own pre-processing
        got = dict(zip(names, ort_model.session.run(list(names), {contract.input.name: x})))
        with torch.no_grad():
            want = dict(zip(names, (t.numpy() for t in model(torch.from_numpy(x)))))
        for name in names:
            a, b = got[name], want[name]
            if a.shape != b.shape:
                raise EdgeError(f"output '{name}': ONNX Runtime gives shape {list(a.shape)}, PyTorch {list(b.shape)}")
            if not (np.isfinite(a).all() and np.isfinite(b).all()):
                raise EdgeError(f"output '{name}' is not finite (ONNX Runtime or PyTorch); refusing to write")
            err = float(np.max(np.abs(a.astype(np.float64) - b)))
            max_abs = max(max_abs, err)
            max_rel = max(max_rel, err / max(float(np.max(np.abs(b))), 1e-12))
            shapes[name] = tuple(a.shape)
        _check_output_sizes(contract, shapes)
        ort_model.decode(got)           # the contract must be able to decode what the graph gives
    from tqdm import tqdm

    tqdm.write(f"ONNX Runtime vs PyTorch on {settings.checks} random images: max abs error {max_abs:.3g}, "
          f"max rel error {max_rel:.3g} (tolerance {settings.rel_tolerance:g})", file=sys.stderr)
    if not max_rel <= settings.rel_tolerance:
        raise EdgeError(f"ONNX Runtime and PyTorch disagree: max rel error {max_rel:.3g} > {settings.rel_tolerance:g} "
                        f"(max abs {max_abs:.3g}); refusing to write {contract.arch}")
    return shapes, max_abs, max_rel


def _check_output_sizes(contract: ModelContract, shapes: Dict[str, Tuple[int, ...]]) -> None:
    d = contract.depth
    if d is None:
        return
    shape = shapes[d.output]
    hw = shape[2:4] if d.layout is Layout.NCHW else shape[1:3]
    want = (contract.input.height // d.stride, contract.input.width // d.stride)
    if tuple(hw) != want:
        raise EdgeError(f"depth output '{d.output}' is {hw[0]}x{hw[1]} but the contract's stride {d.stride} "
                        f"says {want[0]}x{want[1]}")


def _progress(enabled: bool, total: int, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, disable=not enabled, file=sys.stderr, leave=False)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return (text.splitlines()[0] if text else type(exc).__name__)[:300]
