"""The conventions shared by every ``edge-*`` command (ARCHITECTURE.md §10).

- :class:`CliParser` gives every command ``--version``, ``--log-level`` and one-line argument errors, and
  checks the command's optional extra as soon as the arguments are parsed (``--help`` works without it);
- :func:`run_cli` runs a command body and turns an :class:`EdgeError`, or an extra's module that turns out
  to be missing deep inside, into one line on stderr and exit 2;
- :func:`output_file` / :func:`output_folder` create (or refuse) where the results go before the work starts.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import math
import os
import sys
from pathlib import Path
from typing import Any, Callable, NoReturn, Sequence, TypeVar

from edge_landing import __version__
from edge_landing.runtime.core.errors import EdgeError, InputError, MissingExtraError

T = TypeVar("T")
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
LOG_FORMAT = "%(levelname)s %(name)s: %(message)s"

# The import names each optional extra of pyproject.toml provides (tests/test_cli_conventions.py keeps this in
# step with pyproject). A command names its extra and, where it needs less than all of it, which modules.
EXTRA_MODULES: dict[str, tuple[str, ...]] = {
    "export": ("torch", "onnx", "onnxscript", "tqdm"),
    "sim": ("embreex", "trimesh", "tqdm"),
    "bench": ("torch", "onnx", "onnxscript", "tqdm", "matplotlib", "psutil", "openvino", "transformers"),
    "openvino": ("openvino",),
}


def pip_hint(extra: str) -> str:
    return f"pip install 'edge-landing[{extra}]'"


def require_modules(extra: str, modules: Sequence[str] | None = None) -> None:
    """Import every module the command needs from ``extra`` now, or fail in one line naming the install."""
    for name in modules if modules is not None else EXTRA_MODULES[extra]:
        try:
            importlib.import_module(name)
        except ImportError as exc:
            why = (str(exc).splitlines() or ["not found"])[0]
            raise MissingExtraError(f"'{name}' is not installed ({why}); this command needs the {extra} extra: "
                                    f"{pip_hint(extra)}") from None


def configure_logging(level: str) -> None:
    """Root logging at ``level`` (one of LOG_LEVELS) with the project's one-line format."""
    logging.basicConfig(level=level, format=LOG_FORMAT)   # no-op when a handler is already there
    logging.getLogger().setLevel(level)


class CliParser(argparse.ArgumentParser):
    """argparse with the project's conventions: ``--version``, ``--log-level`` (applied when the arguments are
    parsed), bad-argument errors as one InputError line (exit 2 through :func:`run_cli`) instead of the usage
    dump, and the command's optional extra checked right after parsing (so ``--help`` and ``--version`` work
    without it and a missing extra stops the command before any work)."""

    def __init__(self, *args: Any, extra: str | None = None, extra_modules: Sequence[str] | None = None,
                 **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if extra is not None and extra not in EXTRA_MODULES:
            raise ValueError(f"unknown extra {extra!r}")
        self.extra = extra
        self.extra_modules = tuple(extra_modules) if extra_modules is not None else None
        self.add_argument("--version", action="version", version=f"edge-landing {__version__}")
        self.add_argument("--log-level", default="INFO", type=str.upper, choices=LOG_LEVELS,
                          help="logging threshold: DEBUG, INFO (default), WARNING or ERROR")

    def add_no_progress(self) -> None:
        """``--no-progress`` (dest ``no_progress``); ``--quiet``, the old spelling of some tools, still works."""
        self.add_argument("--no-progress", action="store_true", help="no progress bar")
        self.add_argument("--quiet", dest="no_progress", action="store_true", help=argparse.SUPPRESS)

    def parse_known_args(self, args: Sequence[str] | None = None,  # type: ignore[override]
                         namespace: argparse.Namespace | None = None) -> tuple[argparse.Namespace, list[str]]:
        ns, rest = super().parse_known_args(args, namespace)
        level = getattr(ns, "log_level", None)
        if level is not None:
            configure_logging(level)
        if self.extra is not None:
            require_modules(self.extra, self.extra_modules)
        return ns, rest

    def error(self, message: str) -> NoReturn:
        raise InputError(f"{message} (see {self.prog} --help)")


def _missing_extra(exc: ModuleNotFoundError) -> str | None:
    """The extra that provides the module ``exc`` could not find, if it is one of ours."""
    top = (exc.name or "").split(".")[0]
    return next((extra for extra, modules in EXTRA_MODULES.items() if top in modules), None)


def run_cli(main: Callable[[Sequence[str] | None], int | None], argv: Sequence[str] | None = None) -> int:
    """Run a CLI body, turning EdgeError (and a missing extra's module) into one line on stderr, exit 2."""
    configure_logging("INFO")   # until CliParser applies --log-level
    prog = (sys.argv[0].rsplit("/", 1)[-1] or "edge") if sys.argv else "edge"
    try:
        code = main(argv)
    except EdgeError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ModuleNotFoundError as exc:
        # A lazy import of an optional extra deep inside a command: still one line naming what to install.
        extra = _missing_extra(exc)
        if extra is None:
            raise
        print(f"{prog}: error: '{exc.name}' is not installed; {pip_hint(extra)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # stdout was closed early (`edge-eval … | head`): not an error of ours. Point stdout at devnull so
        # the interpreter's final flush does not print a second traceback (Python docs, "SIGPIPE").
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, what a shell reports for a command killed by a closed pipe
    return int(code or 0)


def _writable_folder(folder: Path, what: str) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder {folder} ({what}): {exc.strerror or exc}") from None
    if not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(f"cannot write into {folder} ({what}): permission denied")


def output_file(path: str | os.PathLike[str], what: str) -> Path:
    """Make sure ``path`` can be written before the work starts: its folder is created (with parents) and
    writable, and it is not a folder itself. ``what`` names it in the error, e.g. "the --json file"."""
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{what} {p} is a folder, expected a file path")
    _writable_folder(p.parent if str(p.parent) else Path("."), f"{what} {p}")
    if p.exists() and not os.access(p, os.W_OK):
        raise InputError(f"cannot overwrite {what} {p}: permission denied")
    if p.exists() and not p.is_file():
        raise InputError(f"{what} {p} exists and is not a regular file")
    if p.exists():
        try:   # opened for appending and closed at once: nothing written, nothing truncated
            with open(p, "a"):
                pass
        except OSError as exc:
            raise InputError(f"cannot write {what} {p}: {exc.strerror or exc}") from None
    return p


MAX_THREADS = 256     # more threads than any companion computer has cores: a typo, refused before any work


def check_number(flag: str, value: float, lo: float | None = None, hi: float | None = None, *,
                 lo_open: bool = False, unit: str = "") -> float:
    """``value`` of ``flag`` if it is finite and within [lo, hi] (``lo_open``: lo excluded); else one InputError
    naming the flag and the value (NaN and inf pass no range check on their own: comparisons with NaN are False)."""
    ok = isinstance(value, (int, float)) and math.isfinite(value)
    if ok and lo is not None:
        ok = value > lo if lo_open else value >= lo
    if ok and hi is not None:
        ok = value <= hi
    if not ok:
        low = "" if lo is None else (f"> {lo:g}" if lo_open else f">= {lo:g}")
        high = "" if hi is None else f"<= {hi:g}"
        want = " and ".join(w for w in (low, high) if w) or "finite"
        raise InputError(f"{flag} must be a finite number {want}{' ' + unit if unit else ''}, got {value}")
    return value


def check_seed(flag: str, value: int) -> int:
    """A random seed: a non-negative integer (numpy's generators refuse negative ones with a traceback)."""
    if value < 0:
        raise InputError(f"{flag} must be a non-negative integer, got {value}")
    return value


def check_choice(flag: str, parse: Callable[[str], T], text: str) -> T:
    """``parse(text)`` (e.g. ``Style.from_string``), its one-line InputError prefixed with the flag."""
    try:
        return parse(text)
    except InputError as exc:
        raise InputError(f"{flag}: {exc}") from None


def check_threads(flag: str, value: int) -> int:
    """A thread count: 1 .. MAX_THREADS."""
    if not 1 <= value <= MAX_THREADS:
        raise InputError(f"{flag} must be between 1 and {MAX_THREADS}, got {value}")
    return value


def check_outputs_spare_inputs(outputs: dict[str, str | os.PathLike[str] | None],
                               inputs: dict[str, str | os.PathLike[str] | None]) -> None:
    """Refuse an output path that names one of the inputs (or another output): writing it would destroy the
    input (``--log`` given the model's path). Keys are the flags, for the error."""
    def key(path: str | os.PathLike[str]) -> str:
        return os.path.realpath(os.fspath(path))

    seen: dict[str, str] = {key(p): flag for flag, p in inputs.items() if p}
    for flag, path in outputs.items():
        if not path:
            continue
        k = key(path)
        if k in seen:
            raise InputError(f"{flag} {path} is the same file as {seen[k]}: writing it would overwrite that")
        seen[k] = flag


def output_folder(path: str | os.PathLike[str], what: str) -> Path:
    """Create the folder ``path`` (with parents) now, or fail in one line if it cannot be created or written."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise InputError(f"{what} {p} exists and is not a folder")
    _writable_folder(p, f"{what} {p}")
    return p
