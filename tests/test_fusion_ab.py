"""benchmarks.fusion_ab: two real worker processes fuse the same frames in turn; a base that cannot fuse fails
in one line (exit 2)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from edge_landing.benchmarks import fusion_ab
from edge_landing.runtime.core.errors import InputError
from tests.helpers import one_line_error

ROOT = Path(fusion_ab.__file__).resolve().parents[2]


def test_same_checkout_on_both_sides_fuses_every_frame():
    out = fusion_ab.run(fusion_ab.AbConfig(base=ROOT, frames=10, warmup=2), progress=False)
    assert out["benchmark"] == "fusion_ab" and out["frames"] == 10
    for side in ("this", "base"):
        figures = out[side]
        assert 0 < figures["p50_ms"] <= figures["p90_ms"] <= figures["p99_ms"] < 10_000
        assert figures["cpu_p50_ms"] > 0
    assert out["p50_ratio"] == pytest.approx(out["this"]["p50_ms"] / out["base"]["p50_ms"], abs=1e-3)


def test_a_base_whose_fusion_does_not_import_is_one_line(tmp_path, capsys):
    fuser = tmp_path / "edge_landing" / "runtime" / "fusion" / "fuser.py"
    fuser.parent.mkdir(parents=True)
    for pkg in (tmp_path / "edge_landing", fuser.parent.parent, fuser.parent):
        (pkg / "__init__.py").write_text("")
    fuser.write_text("raise ImportError('broken on purpose')\n")
    with pytest.raises(InputError, match="did not start"):
        fusion_ab.run(fusion_ab.AbConfig(base=tmp_path, frames=10, warmup=0), progress=False)
    one_line_error(capsys, fusion_ab.main, ["--base", str(tmp_path), "--frames", "10"], "--base")


def test_a_worker_that_dies_mid_run_is_named_and_cleaned_up(tmp_path):
    stderr = tmp_path / "base.stderr"
    stderr.write_text("Traceback (most recent call last):\nMemoryError: out of memory\n")
    proc = subprocess.Popen([sys.executable, "-c", "pass"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    proc.wait()
    with pytest.raises(InputError, match="base side's fusion stopped mid-run .MemoryError: out of memory"):
        fusion_ab._frame(proc, "base", stderr)
    fusion_ab._stop(proc)                                   # a broken pipe is not an error here
    assert proc.returncode == 0 and proc.stdout is not None and proc.stdout.closed
