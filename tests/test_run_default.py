"""The README's first command: ``edge-run`` with no arguments flies the built-in synthetic approach."""
import io

import pytest

pytest.importorskip("embreex")

from edge_landing.cli.run import config_from_args, run


def test_edge_run_with_no_camera_flies_the_builtin_sim_and_finds_targets():
    out = io.StringIO()
    assert run(config_from_args(["--max-frames", "12"]), out=out) == 0
    text = out.getvalue()
    assert any(line.startswith("edge-run: sim") for line in text.splitlines()), text
    summary = [line for line in text.splitlines() if line.startswith("targets ")]
    assert summary, text
    frames = int(summary[0].split()[1].split("/")[1])
    assert frames == 12
