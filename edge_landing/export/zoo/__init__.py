"""The model zoo: the published networks (and ours), each described by one ArchSpec.

    from edge_landing.export.zoo import get_arch
    spec = get_arch("safeuav-small")
    model = spec.build(Task.HVO)                     # torch.nn.Module
    contract = spec.contract(Task.HVO, 240, 320)     # runtime ModelContract for the ONNX metadata

Each architecture lives in its own module that defines ``ARCH_SPEC``; modules are imported lazily so that
building one network does not import the others.
"""
from __future__ import annotations

import importlib

from edge_landing.runtime.core.errors import InputError

from .registry import ArchSpec

# edge.arch name -> module defining ARCH_SPEC
ARCH_MODULES = {
    "densedepth": "edge_landing.export.zoo.densedepth",
    "adabins": "edge_landing.export.zoo.adabins",
    "safeuav-large": "edge_landing.export.zoo.safeuav",
    "safeuav-small": "edge_landing.export.zoo.safeuav",
    "edgenet": "edge_landing.export.zoo.edgenet",
    # speed peer only (random weights, needs transformers): edge-bench --models depth-anything-v2-small
    "depth-anything-v2-small": "edge_landing.export.zoo.depth_anything",
}


def arch_names() -> tuple:
    return tuple(ARCH_MODULES)


def get_arch(name: str) -> ArchSpec:
    """The ArchSpec for an edge.arch name; an unknown name is one clear error."""
    if name not in ARCH_MODULES:
        raise InputError(f"unknown architecture '{name}'; expected one of: {', '.join(ARCH_MODULES)}")
    module = importlib.import_module(ARCH_MODULES[name])
    specs = getattr(module, "ARCH_SPECS", None) or {module.ARCH_SPEC.name: module.ARCH_SPEC}
    return specs[name]


__all__ = ["ArchSpec", "arch_names", "get_arch"]
