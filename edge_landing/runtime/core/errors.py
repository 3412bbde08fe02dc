"""User-facing errors (ARCHITECTURE.md §10).

Entry points raise an :class:`EdgeError` subclass whose message says what is wrong, where, and what was
expected; ``edge_landing.cli.common.run_cli`` turns it into one line on stderr and exit 2. Per-frame code
never raises these: it marks the frame invalid and logs why.
"""
from __future__ import annotations

from types import ModuleType


class EdgeError(Exception):
    """A problem with the user's input or environment, explained in one line."""


class ContractError(EdgeError):
    """An ONNX file without the model contract of ARCHITECTURE.md §5, or with a broken one."""


class SceneError(EdgeError):
    """A scene folder (ARCHITECTURE.md §4) that is missing, empty or malformed."""


class InputError(EdgeError):
    """A bad argument or data value given to an entry point."""


class MissingExtraError(EdgeError):
    """An optional dependency is not installed."""


def require_extra(module: str, extra: str) -> ModuleType:
    """Import an optional dependency or fail with a hint naming the extra that provides it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtraError(
            f"this feature needs the '{module}' package, which is not installed: "
            f"pip install 'edge-landing[{extra}]' ({exc})"
        ) from exc
