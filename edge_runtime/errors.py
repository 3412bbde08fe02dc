"""User-facing errors and the one-line CLI convention (DESIGN.md §10).

Entry points raise an :class:`EdgeError` subclass whose message says what is wrong, where, and what was
expected. :func:`run_cli` turns it into one line on stderr and a non-zero exit. Per-frame code never
raises these: it marks the frame invalid and logs why.
"""
from __future__ import annotations

import argparse
import logging
import sys
from typing import Callable, Sequence

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130


class EdgeError(Exception):
    """A problem with the user's input or environment, explained in one line."""


class ContractError(EdgeError):
    """An ONNX file without the model contract of DESIGN.md §5, or with a broken one."""


class SceneError(EdgeError):
    """A scene folder (DESIGN.md §4) that is missing, empty or malformed."""


class InputError(EdgeError):
    """A bad argument or data value given to an entry point."""


class MissingExtraError(EdgeError):
    """An optional dependency is not installed."""


def require_extra(module: str, extra: str):
    """Import an optional dependency or fail with a hint naming the extra that provides it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtraError(
            f"this feature needs the '{module}' package, which is not installed: "
            f"pip install 'edge-landing[{extra}]' ({exc})"
        ) from exc


class CliParser(argparse.ArgumentParser):
    """argparse whose bad-argument errors are one InputError line (exit 2 through :func:`run_cli`) instead
    of the multi-line usage dump; ``--help`` is unchanged."""

    def error(self, message: str):
        raise InputError(f"{message} (see {self.prog} --help)")


def run_cli(main: Callable[[Sequence[str] | None], int | None], argv: Sequence[str] | None = None) -> int:
    """Run a CLI body, turning EdgeError into one line on stderr and a non-zero exit code."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    prog = (sys.argv[0].rsplit("/", 1)[-1] or "edge") if sys.argv else "edge"
    try:
        code = main(argv)
    except EdgeError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # stdout was closed early (`edge-eval … | head`): not an error of ours. Point stdout at devnull so
        # the interpreter's final flush does not print a second traceback (Python docs, "SIGPIPE").
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, what a shell reports for a command killed by a closed pipe
    return int(code or 0)
