"""The direction of imports (ARCHITECTURE.md §2): the drone side loads without any workstation part.

Each check runs in a fresh interpreter (this pytest process has long since imported numpy, torch and the
rest). Before anything else is imported there, a meta-path finder refuses the blocked names as if they
were not installed, and records who asked for them. The drone side is every module under
``edge_landing.runtime`` (found by walking the package, so a new module is covered without editing this
file) plus the ``edge-run`` command line. A check fails when a blocked module ends up in ``sys.modules``,
or when code of this project asked for one at all: a ``try: import … except ImportError`` in our own code
would otherwise hide a wrong arrow. Third-party packages probing for an optional dependency of theirs are
reported but allowed.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any, Dict

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]

# What the drone side must never need: the [export] and [sim] extras' packages, the workstation parts, and
# the command lines other than edge-run's.
BLOCKED = ("torch", "onnx", "trimesh", "embreex",
           "edge_landing.sim", "edge_landing.export", "edge_landing.benchmarks", "edge_landing.evaluation",
           "edge_landing.calibration", "edge_landing.cli.eval_cli")

# Runs first in the child: installs the blocking finder, then executes the check's body. The body leaves
# its findings in RESULT; the finder's log is added and everything is printed as one JSON line.
_PRELUDE = textwrap.dedent('''
    import json, sys

    BLOCKED = {blocked!r}
    ASKED = []      # (blocked name, module that asked): every refused import

    def _blocked(name):
        return any(name == b or name.startswith(b + ".") for b in BLOCKED)

    def _asker():
        """The module whose code triggered this import (the first frame outside the import machinery)."""
        f = sys._getframe(2)
        while f is not None and (f.f_code.co_filename.startswith("<frozen") or "importlib" in f.f_code.co_filename):
            f = f.f_back
        return f.f_globals.get("__name__", "?") if f is not None else "?"

    class BlockWorkstation:
        """Refuses the blocked names as if they were not installed."""

        @classmethod
        def find_spec(cls, name, path=None, target=None):
            if _blocked(name):
                ASKED.append((name, _asker()))
                raise ModuleNotFoundError(f"blocked by tests/test_layering.py: {{name}}", name=name)
            return None

    sys.meta_path.insert(0, BlockWorkstation)
    RESULT = {{}}
''').format(blocked=BLOCKED)

_EPILOGUE = textwrap.dedent('''
    RESULT["loaded"] = sorted(m for m in sys.modules if _blocked(m))
    RESULT["asked"] = ASKED
    print("RESULT " + json.dumps(RESULT))
''')


def _run_blocked(body: str, timeout_s: float = 240.0) -> Dict[str, Any]:
    """Run ``body`` in a fresh interpreter with the workstation parts unimportable; its RESULT dict."""
    code = _PRELUDE + textwrap.dedent(body) + _EPILOGUE
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=timeout_s)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, (
        f"the check's interpreter failed (exit {proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    result: Dict[str, Any] = json.loads(lines[-1][len("RESULT "):])
    return result


def _assert_clean(result: Dict[str, Any]) -> None:
    ours = list(dict.fromkeys((name, asker) for name, asker in result["asked"] if asker.startswith("edge_landing")))
    assert not ours, "drone-side code asked for workstation parts: " + ", ".join(
        f"{asker} imports {name}" for name, asker in ours)
    assert result["loaded"] == [], f"workstation modules loaded on the drone side: {result['loaded']}"


def test_drone_side_imports_without_torch_sim_export_benchmarks_or_evaluation() -> None:
    result = _run_blocked('''
        import importlib, pkgutil
        import edge_landing.runtime as runtime

        failed = []
        def onerror(name):
            failed.append(f"{name}: {sys.exc_info()[1]!r}")

        names = [m.name for m in pkgutil.walk_packages(runtime.__path__, runtime.__name__ + ".", onerror=onerror)]
        names += ["edge_landing.cli.common", "edge_landing.cli.run"]
        for name in names:
            try:
                importlib.import_module(name)
            except Exception as exc:
                failed.append(f"{name}: {exc!r}")
        RESULT["modules"] = names
        RESULT["failed"] = failed
    ''')
    _assert_clean(result)
    assert result["failed"] == [], "drone-side modules that do not import:\n" + "\n".join(result["failed"])
    # The walk found the whole drone side, not an empty package (one module per role at least).
    modules = set(result["modules"])
    for expected in ("edge_landing.runtime.core.messages", "edge_landing.runtime.perception.inference",
                     "edge_landing.runtime.fusion.fuser", "edge_landing.runtime.io.mavlink_link",
                     "edge_landing.runtime.io.sources", "edge_landing.runtime.pipeline",
                     "edge_landing.runtime.models", "edge_landing.cli.run"):
        assert expected in modules


def test_edge_run_flies_frames_without_the_workstation_parts(tmp_path: Path) -> None:
    """Importing is not all: the per-frame path (inference, fusion, overlay, decision log) may import lazily."""
    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:06d}.png"), rng.integers(0, 256, (96, 128, 3), dtype=np.uint8))
    log_path, record = tmp_path / "t.jsonl", tmp_path / "overlay.mp4"
    result = _run_blocked(f'''
        from edge_landing.cli.run import main
        RESULT["exit"] = main(["--camera", {str(folder)!r}, "--max-frames", "3", "--threads", "1",
                               "--log", {str(log_path)!r}, "--record", {str(record)!r}])
    ''')
    assert result["exit"] == 0
    _assert_clean(result)
    header, *decisions = [json.loads(line) for line in log_path.read_text().splitlines()]
    assert "run" in header
    assert [d["frame"] for d in decisions] == [0, 1, 2]
    assert record.stat().st_size > 0


def test_importing_the_namespace_loads_nothing() -> None:
    """``import edge_landing`` (for ``__version__``, or on the way to any subpackage) costs nothing."""
    code = ("import sys, json, edge_landing; "
            "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in "
            "('numpy', 'onnxruntime', 'cv2', 'pymavlink', 'torch', 'edge_landing'))))")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == ["edge_landing"]
