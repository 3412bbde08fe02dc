"""Loading the authors' checkpoints into our re-implementations, strictly and with clear errors.

Shared by every architecture of the zoo::

    from edge_landing.export.checkpoints import read_checkpoint, model_state, load_state_dict_strict
    obj = read_checkpoint(path)                              # torch.load, weights only, one clear error
    with trusted_checkpoints(): obj = read_checkpoint(path)  # full unpickling, for files you trust
    sd = model_state(obj, path)                              # the state_dict, without "module." prefixes
    load_state_dict_strict(model, sd, where=str(path))       # InputError names the parameter and both shapes

SafeUAV checkpoints hold no names, only an ordered list of tensors: ``load_ordered_tensors`` assigns them
by position to ``module.parameters()`` (registration order).
"""
from __future__ import annotations

import contextvars
import os
import re
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator, List, Mapping, Optional, Sequence

import torch

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.perception.inference import file_sha256

# Keys under which training scripts commonly nest the state_dict in a checkpoint dict.
NESTED_STATE_KEYS = ("model", "state_dict", "model_state_dict")
# How many names an error lists before it says "and N more" (keeps the message one readable line).
_MAX_NAMES = 5


# Unpickling may run code from the file: only tensors and plain containers are read unless the caller
# says the file is trusted (``with trusted_checkpoints(): ...``, edge-export --trust-checkpoint).
_TRUSTED = contextvars.ContextVar("edge_trusted_checkpoints", default=False)


@contextmanager
def trusted_checkpoints(enabled: bool = True) -> Iterator[None]:
    """Within this block read_checkpoint unpickles fully (old files that also hold numpy or class objects)."""
    token = _TRUSTED.set(enabled)
    try:
        yield
    finally:
        _TRUSTED.reset(token)


def read_checkpoint(path: os.PathLike | str) -> object:
    """torch.load with ``weights_only=True`` (no code from the file runs); any failure is one InputError."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"checkpoint {path} does not exist")
    trusted = _TRUSTED.get()
    try:
        return torch.load(str(path), map_location="cpu", weights_only=not trusted)
    except Exception as exc:  # torch raises pickle/zip/runtime errors of many kinds for bad files
        text = str(exc)
        unsafe = re.search(r"Unsupported global: GLOBAL ([\w.]+)", text)
        if unsafe and not trusted:
            raise InputError(f"checkpoint {path} holds Python objects besides tensors (e.g. {unsafe.group(1)}), "
                             f"which are not unpickled from an untrusted file; if you trust its origin, pass "
                             f"--trust-checkpoint") from None
        detail = re.search(r"WeightsUnpickler error: \s*(.+)", text)
        first = detail.group(1).strip() if detail else (text.strip().splitlines() or [type(exc).__name__])[0]
        raise InputError(f"checkpoint {path} could not be read as a PyTorch file ({first[:200]}); "
                         f"expected a file written by torch.save") from None


def source_info(path: os.PathLike | str) -> dict:
    """What edge.source records about a checkpoint: its file name and sha256."""
    path = Path(path)
    return {"weights": "checkpoint", "checkpoint": path.name, "sha256": file_sha256(path)}


def unwrap_state_dict(obj: object, where: str) -> dict:
    """The name -> tensor mapping of a checkpoint that is either a state_dict or a dict nesting one."""
    if not isinstance(obj, Mapping):
        raise InputError(f"{where}: expected a state_dict (a dict of name -> tensor), got a {type(obj).__name__}")
    for key in NESTED_STATE_KEYS:
        inner = obj.get(key)
        if isinstance(inner, Mapping) and inner and all(torch.is_tensor(v) for v in inner.values()):
            return dict(inner)
    tensors = {k: v for k, v in obj.items() if torch.is_tensor(v)}
    if not tensors:
        raise InputError(f"{where}: holds no tensors (top-level keys: {_names(obj.keys())}); "
                         f"expected a state_dict or a dict with one of {list(NESTED_STATE_KEYS)}")
    return tensors


def strip_prefix(state_dict: Mapping[str, torch.Tensor], prefix: str = "module.") -> dict:
    """Remove ``prefix`` from every key that has it (DataParallel saves keys as ``module.<name>``)."""
    return {(k[len(prefix):] if k.startswith(prefix) else k): v for k, v in state_dict.items()}


def model_state(obj: object, where: str) -> dict:
    """The state_dict a checkpoint holds, without DataParallel's ``module.`` prefixes."""
    return strip_prefix(unwrap_state_dict(obj, where), "module.")


def drop_keys(state_dict: Mapping[str, torch.Tensor], prefix: str) -> dict:
    """The state_dict without the keys starting with ``prefix`` (e.g. an unused classifier)."""
    return {k: v for k, v in state_dict.items() if not k.startswith(prefix)}


def load_state_dict_strict(module: torch.nn.Module, state_dict: Mapping[str, torch.Tensor], where: str) -> None:
    """Load every parameter and buffer by name; any missing, unexpected or mis-shaped key is one InputError.

    The message names the first offending parameter with both shapes, so a wrong checkpoint (another
    architecture, another number of bins or classes) is recognisable at a glance.
    """
    expected = module.state_dict()
    mismatched = [(k, tuple(v.shape), tuple(expected[k].shape)) for k, v in state_dict.items()
                  if k in expected and tuple(v.shape) != tuple(expected[k].shape)]
    if mismatched:
        name, got, want = mismatched[0]
        more = f" (and {len(mismatched) - 1} more mismatched)" if len(mismatched) > 1 else ""
        raise InputError(f"{where}: parameter '{name}' has shape {list(got)} in the checkpoint but the model "
                         f"expects {list(want)}{more}; is this a checkpoint of this architecture and task?")
    # BatchNorm's step counter is unused in eval and absent from checkpoints older than PyTorch 0.4.1
    # (and from those converted from Keras): keep the module's own value rather than refuse the file.
    state_dict = dict(state_dict)
    for k in expected:
        if k not in state_dict and k.endswith(".num_batches_tracked"):
            state_dict[k] = expected[k]
    missing = [k for k in expected if k not in state_dict]
    unexpected = [k for k in state_dict if k not in expected]
    if missing or unexpected:
        parts = []
        if missing:
            parts.append(f"missing {len(missing)} key(s): {_names(missing)}")
        if unexpected:
            parts.append(f"unexpected {len(unexpected)} key(s): {_names(unexpected)}")
        raise InputError(f"{where}: checkpoint does not match the model ({'; '.join(parts)})")
    non_tensor = [k for k, v in state_dict.items() if not torch.is_tensor(v)]
    if non_tensor:
        raise InputError(f"{where}: entries are not tensors: {_names(non_tensor)}")
    with torch.no_grad():
        module.load_state_dict(state_dict, strict=True)


def ordered_tensor_list(obj: object, where: str, keys: Sequence[str] = ("weights", "params")) -> List[torch.Tensor]:
    """The ordered list of tensors stored under the first of ``keys`` present in a checkpoint dict."""
    if not isinstance(obj, Mapping):
        raise InputError(f"{where}: expected a dict with an ordered list of tensors under one of {list(keys)}, "
                         f"got a {type(obj).__name__}")
    for key in keys:
        if key in obj:
            tensors = obj[key]
            if not isinstance(tensors, (list, tuple)) or not all(torch.is_tensor(t) for t in tensors):
                raise InputError(f"{where}: '{key}' should be a list of tensors, got a {type(tensors).__name__}")
            return list(tensors)
    raise InputError(f"{where}: no key {' or '.join(repr(k) for k in keys)} (top-level keys: {_names(obj.keys())}); "
                     f"expected a SafeUAV checkpoint (an ordered list of parameter tensors)")


def load_ordered_tensors(module: torch.nn.Module, tensors: Sequence[torch.Tensor], where: str) -> None:
    """Assign ``tensors`` to ``module``'s parameters by position (registration order); strict on count and shape."""
    params = list(module.named_parameters())
    if len(tensors) != len(params):
        raise InputError(f"{where}: checkpoint holds {len(tensors)} tensors but the model has {len(params)} "
                         f"parameters; is this a checkpoint of this architecture and task?")
    for index, ((name, param), tensor) in enumerate(zip(params, tensors)):
        if tuple(tensor.shape) != tuple(param.shape):
            raise InputError(f"{where}: tensor #{index} (parameter '{name}') has shape {list(tensor.shape)} in the "
                             f"checkpoint but the model expects {list(param.shape)}; is this a checkpoint of this "
                             f"architecture and task?")
    with torch.no_grad():
        for (_, param), tensor in zip(params, tensors):
            param.copy_(tensor.to(param.dtype))


def count_parameters(module: torch.nn.Module, prefix: Optional[str] = None) -> int:
    """Number of parameters (optionally only those whose name starts with ``prefix``)."""
    return sum(p.numel() for n, p in module.named_parameters() if prefix is None or n.startswith(prefix))


def _names(names: Iterable) -> str:
    names = [str(n) for n in names]
    shown = ", ".join(names[:_MAX_NAMES])
    return shown + (f", ... ({len(names) - _MAX_NAMES} more)" if len(names) > _MAX_NAMES else "")
