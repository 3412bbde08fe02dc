"""The one-line CLI convention shared by every ``edge-*`` command (ARCHITECTURE.md §10).

:func:`run_cli` runs a command body and turns an :class:`EdgeError` into one line on stderr and exit 2.
"""
from __future__ import annotations

import argparse
import logging
import sys
from typing import Callable, NoReturn, Sequence

from edge_landing.runtime.core.errors import EdgeError, InputError

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130


class CliParser(argparse.ArgumentParser):
    """argparse whose bad-argument errors are one InputError line (exit 2 through :func:`run_cli`) instead
    of the multi-line usage dump; ``--help`` is unchanged."""

    def error(self, message: str) -> NoReturn:
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
