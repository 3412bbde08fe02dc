"""Whether OpenVINO can compile and run a model file on this CPU, asked of a child process (ARCHITECTURE.md §9).

OpenVINO's CPU plugin can take the whole process down instead of raising: 2026.4.1 died of SIGSEGV in
``compile_model`` on DenseDepth's INT8 QDQ file on an AVX2-only AMD EPYC (the FP32 file compiled). A drone's
runtime probing for the faster runtime, or a benchmark an hour into its run, must not die of a peer's bug, so a
file is first compiled and run once in a child; only a file that survived that is compiled in this process.

    ok, why = runs_in_child(Path("model.int8.onnx"), threads=2)
"""
from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path
from typing import Optional, Sequence, Tuple

from edge_landing.runtime.perception.backend import RUN_PRECISION

CHECK_TIMEOUT_S = 300.0      # a large model's first compile takes tens of seconds on 2 cores


_DEFAULT = "default"         # the child's word for "OpenVINO's own default precision" (precision=None)


def runs_in_child(path: Path, threads: int, timeout_s: float = CHECK_TIMEOUT_S,
                  precision: Optional[str] = RUN_PRECISION) -> Tuple[bool, str]:
    """(True, "") when a child process compiled ``path`` with OpenVINO and ran it once; else (False, why).

    ``precision`` as in ``backend.OpenVinoSession``: a different precision is a different compile, which can
    crash where the other does not."""
    cmd = [sys.executable, "-m", "edge_landing.runtime.perception.openvino_check", str(path), str(threads),
           precision or _DEFAULT]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return False, f"OpenVINO did not compile and run it within {timeout_s:.0f} s"
    except OSError as exc:
        return False, f"could not start the OpenVINO check: {exc}"
    if done.returncode == 0:
        return True, ""
    if done.returncode < 0:
        try:
            name = signal.Signals(-done.returncode).name
        except ValueError:
            name = f"signal {-done.returncode}"
        return False, f"OpenVINO crashed ({name}) compiling or running it on this CPU"
    last = (done.stderr.strip().splitlines() or [f"exit code {done.returncode}"])[-1]
    return False, f"OpenVINO cannot run it: {last[:200]}"


def _compile_and_run(path: str, threads: int, precision: Optional[str]) -> None:
    """The session edge-run would load (``backend.OpenVinoSession``: the same compile settings), run once on zeros
    (every contract input is a float32 image)."""
    import numpy as np

    from edge_landing.runtime.perception.backend import OpenVinoSession

    session = OpenVinoSession(Path(path), threads, precision=precision)
    ports = session.get_inputs()
    if any(d is None for p in ports for d in p.shape):
        return                                    # compiled; nothing fixed to run it on
    session.run(None, {p.name: np.zeros([int(d) for d in p.shape if d is not None], np.float32) for p in ports})


def main(argv: Optional[Sequence[str]] = None) -> int:
    given = list(sys.argv[1:] if argv is None else argv)
    args = list(given)
    if len(args) == 2:
        args.append(RUN_PRECISION)
    if len(args) != 3 or not args[1].isdigit() or not Path(args[0]).is_file() or args[2] not in (RUN_PRECISION, _DEFAULT):
        print(f"usage: python -m edge_landing.runtime.perception.openvino_check MODEL.onnx THREADS [{RUN_PRECISION}|default] "
              f"(got {given})", file=sys.stderr)
        return 2
    try:
        _compile_and_run(args[0], int(args[1]), None if args[2] == _DEFAULT else args[2])
    except Exception as exc:  # OpenVINO raises its own untyped errors: one line for the parent
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(first, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
