"""The ONNX model contract (ARCHITECTURE.md §5): written once at export, read once at load.

Every exported model carries JSON under these ``metadata_props`` keys; the runtime needs nothing else to
pre-process an image and decode the outputs, so it has no per-architecture code.

Example::

    contract = ModelContract(
        arch="safeuav-small", task=Task.HVO,
        input=InputSpec(name="image", layout=Layout.NHWC, height=240, width=320),
        hvo=HvoSpec(output="hvo_logits", layout=Layout.NHWC),
        source={"checkpoint": None, "note": "random weights"},
    )
    props = contract.to_metadata()            # dict[str, str] for onnx metadata_props
    assert ModelContract.from_metadata(props) == contract
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from typing import Any, Mapping, Optional

import numpy as np

from edge_landing.runtime.core.choices import ChoiceEnum
from edge_landing.runtime.core.errors import ContractError
from edge_landing.runtime.core.labels import HVO_CLASSES

KEY_ARCH = "edge.arch"
KEY_TASK = "edge.task"
KEY_INPUT = "edge.input"
KEY_DEPTH = "edge.depth"
KEY_HVO = "edge.hvo"
KEY_SOURCE = "edge.source"
KEY_QUANTIZATION = "edge.quantization"
REQUIRED_KEYS = (KEY_ARCH, KEY_TASK, KEY_INPUT)


class _StrEnum(ChoiceEnum):
    """Contract enums: a bad value in a model's metadata is a ContractError."""

    @classmethod
    def _error(cls) -> type:
        return ContractError


class Task(_StrEnum):
    DEPTH = "depth"
    HVO = "hvo"
    DEPTH_HVO = "depth+hvo"

    @property
    def has_depth(self) -> bool:
        return self in (Task.DEPTH, Task.DEPTH_HVO)

    @property
    def has_hvo(self) -> bool:
        return self in (Task.HVO, Task.DEPTH_HVO)


class Layout(_StrEnum):
    NCHW = "NCHW"
    NHWC = "NHWC"


class DepthConvention(_StrEnum):
    METRIC = "metric"          # output is metres (AdaBins)
    INVERSE = "inverse"        # metres = clip(max_depth / y, min_depth, max_depth) (DenseDepth)
    NORMALIZED = "normalized"  # metres = y * max_depth (SafeUAV, max 323.485)


@dataclass(frozen=True)
class InputSpec:
    """How to turn an RGB uint8 image into the network input: x = (rgb * scale - mean) / std."""

    name: str
    layout: Layout
    height: int
    width: int
    color: str = "RGB"
    scale: float = 1.0 / 255.0
    mean: tuple[float, ...] = (0.0, 0.0, 0.0)
    std: tuple[float, ...] = (1.0, 1.0, 1.0)

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "layout": self.layout.value, "height": self.height, "width": self.width,
                "color": self.color, "scale": self.scale, "mean": list(self.mean), "std": list(self.std)}

    @staticmethod
    def from_json(d: Mapping[str, Any]) -> InputSpec:
        spec = InputSpec(name=str(d["name"]), layout=Layout.from_string(d["layout"]), height=int(d["height"]),
                         width=int(d["width"]), color=str(d.get("color", "RGB")),
                         scale=float(d.get("scale", 1.0 / 255.0)),
                         mean=tuple(float(v) for v in d.get("mean", (0.0, 0.0, 0.0))),
                         std=tuple(float(v) for v in d.get("std", (1.0, 1.0, 1.0))))
        if spec.height <= 0 or spec.width <= 0:
            raise ContractError(f"edge.input height/width must be positive, got {spec.height}x{spec.width}")
        if spec.color not in ("RGB", "BGR"):
            raise ContractError(f"edge.input color '{spec.color}' is not supported; expected RGB or BGR")
        if len(spec.mean) != 3 or len(spec.std) != 3 or min(spec.std) <= 0:
            raise ContractError(f"edge.input mean/std must be 3 values with std > 0, got {spec.mean} / {spec.std}")
        return spec


@dataclass(frozen=True)
class DepthSpec:
    """Where the depth output is and how to turn it into metres.

    ``stride``: input size / output size (2 for DenseDepth and AdaBins, 1 for SafeUAV). ``layout`` says where
    the single channel is (N1HW or NHW1). ``min_depth``/``max_depth`` (metres) clamp the decoded depth.
    """

    output: str
    convention: DepthConvention
    min_depth: float
    max_depth: float
    stride: int = 1
    layout: Layout = Layout.NCHW

    def to_json(self) -> dict[str, Any]:
        return {"output": self.output, "stride": self.stride, "convention": self.convention.value,
                "min_depth": self.min_depth, "max_depth": self.max_depth, "layout": self.layout.value}

    @staticmethod
    def from_json(d: Mapping[str, Any]) -> DepthSpec:
        spec = DepthSpec(output=str(d["output"]), convention=DepthConvention.from_string(d["convention"]),
                         min_depth=float(d["min_depth"]), max_depth=float(d["max_depth"]),
                         stride=int(d.get("stride", 1)), layout=Layout.from_string(d.get("layout", "NCHW")))
        if not 0 < spec.min_depth < spec.max_depth:
            raise ContractError(f"edge.depth needs 0 < min_depth < max_depth, got {spec.min_depth}, {spec.max_depth}")
        return spec

    def to_metres(self, y: np.ndarray) -> np.ndarray:
        """Decode the raw H×W output into metres (float32); non-finite values become NaN."""
        y = y.astype(np.float32, copy=False)
        with np.errstate(divide="ignore", invalid="ignore"):
            d: np.ndarray
            if self.convention is DepthConvention.METRIC:
                d = y.copy()
            elif self.convention is DepthConvention.INVERSE:
                d = self.max_depth / y
            else:
                d = y * self.max_depth
        d = np.clip(d, self.min_depth, self.max_depth).astype(np.float32)
        d[~np.isfinite(y)] = np.nan
        return d


@dataclass(frozen=True)
class HvoSpec:
    """Where the HVO logits are (3 classes) and their layout."""

    output: str
    layout: Layout = Layout.NCHW
    classes: tuple[str, ...] = HVO_CLASSES

    def to_json(self) -> dict[str, Any]:
        return {"output": self.output, "layout": self.layout.value, "classes": list(self.classes)}

    @staticmethod
    def from_json(d: Mapping[str, Any]) -> HvoSpec:
        spec = HvoSpec(output=str(d["output"]), layout=Layout.from_string(d.get("layout", "NCHW")),
                       classes=tuple(d.get("classes", HVO_CLASSES)))
        if tuple(spec.classes) != HVO_CLASSES:
            raise ContractError(f"edge.hvo classes must be {list(HVO_CLASSES)}, got {list(spec.classes)}")
        return spec


@dataclass(frozen=True)
class ModelContract:
    """All the contract keys of one model."""

    arch: str
    task: Task
    input: InputSpec
    depth: Optional[DepthSpec] = None
    hvo: Optional[HvoSpec] = None
    source: dict[str, Any] = field(default_factory=dict)
    quantization: Optional[dict[str, Any]] = None

    def __post_init__(self) -> None:
        if self.task.has_depth != (self.depth is not None) or self.task.has_hvo != (self.hvo is not None):
            raise ContractError(f"edge.task '{self.task}' does not match the heads described "
                                f"(edge.depth {'present' if self.depth else 'missing'}, "
                                f"edge.hvo {'present' if self.hvo else 'missing'})")

    def with_quantization(self, settings: Mapping[str, Any]) -> ModelContract:
        return replace(self, quantization=dict(settings))

    def to_metadata(self) -> dict[str, str]:
        """The ``metadata_props`` entries (all values are JSON strings, edge.arch/edge.task plain strings)."""
        props = {KEY_ARCH: self.arch, KEY_TASK: self.task.value, KEY_INPUT: json.dumps(self.input.to_json()),
                 KEY_SOURCE: json.dumps(self.source, sort_keys=True, default=str)}
        if self.depth is not None:
            props[KEY_DEPTH] = json.dumps(self.depth.to_json())
        if self.hvo is not None:
            props[KEY_HVO] = json.dumps(self.hvo.to_json())
        if self.quantization is not None:
            props[KEY_QUANTIZATION] = json.dumps(self.quantization, sort_keys=True, default=str)
        return props

    @staticmethod
    def from_metadata(props: Mapping[str, str], where: str = "model") -> ModelContract:
        """Parse and validate; any problem raises ContractError naming the key and the file."""
        missing = [k for k in REQUIRED_KEYS if k not in props]
        if missing:
            raise ContractError(f"{where} has no model contract: metadata key(s) {', '.join(missing)} missing "
                                f"(expected the edge.* keys of ARCHITECTURE.md §5; export it with edge-export)")
        try:
            task = Task.from_string(props[KEY_TASK])
            return ModelContract(
                arch=str(props[KEY_ARCH]), task=task,
                input=InputSpec.from_json(_load(props, KEY_INPUT)),
                depth=DepthSpec.from_json(_load(props, KEY_DEPTH)) if KEY_DEPTH in props else None,
                hvo=HvoSpec.from_json(_load(props, KEY_HVO)) if KEY_HVO in props else None,
                source=_load(props, KEY_SOURCE) if KEY_SOURCE in props else {},
                quantization=_load(props, KEY_QUANTIZATION) if KEY_QUANTIZATION in props else None,
            )
        except ContractError as exc:
            raise ContractError(f"{where}: broken model contract: {exc}") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise ContractError(f"{where}: broken model contract: bad or missing field {exc}") from None


def _load(props: Mapping[str, str], key: str) -> Any:
    try:
        return json.loads(props[key])
    except json.JSONDecodeError as exc:
        raise ContractError(f"metadata key {key} is not valid JSON ({exc})") from None
