"""ArchSpec: everything the exporter, trainer and benchmark need to know about one architecture."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional, Tuple

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.perception.contract import Task


def require_task(arch: str, task: Task, available: Tuple[Task, ...]) -> None:
    """One clear error when a network is asked for a head it does not have."""
    if task not in available:
        heads = " / ".join(t.value for t in available)
        expected = ", ".join(f"'{t.value}'" for t in available)
        raise InputError(f"{arch} has only a {heads} head; task '{task}' is not available (expected {expected})")


@dataclass(frozen=True)
class ArchSpec:
    """One architecture of the zoo.

    build(task, **options) -> torch.nn.Module whose forward takes the *preprocessed* input tensor in the
        contract's layout (NCHW or NHWC, float32) and returns a tuple of tensors named ``output_names(task)``.
    contract(task, height, width, **options) -> ModelContract (source left empty; the exporter fills it).
    load_checkpoint(module, path) -> dict: loads the authors' checkpoint format into ``module`` (strict; a
        mismatch raises InputError naming the parameter and both shapes); returns info for edge.source.
    options: the architecture's build options and their defaults (e.g. {"bins": 256, "max_depth": 10.0}).
    init_checkpoint(module, path) -> dict, optional: what ``edge-train --init`` uses instead of load_checkpoint
        (e.g. EdgeNet widens a narrower checkpoint without changing what it computes).
    """

    name: str
    paper: str
    tasks: Tuple[Task, ...]
    default_task: Task
    input_hw: Tuple[int, int]
    size_multiple: int
    build: Callable
    contract: Callable
    output_names: Callable
    load_checkpoint: Callable
    options: dict = field(default_factory=dict)
    min_hw: Tuple[int, int] = (32, 32)
    init_checkpoint: Optional[Callable] = None
