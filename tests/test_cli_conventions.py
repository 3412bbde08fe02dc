"""Every edge-* command keeps the project's CLI conventions (ARCHITECTURE.md §10), run as the installed console
scripts in subprocesses: ``--help`` and ``--version`` answer with exit 0; a missing optional extra (hidden
from the import system) is one line naming the pip install, exit 2, before any output is written;
``--log-level`` and the ``--no-progress``/``--quiet`` spellings; output folders settled before the work."""
from __future__ import annotations

import json
import logging
import os
import re
import subprocess
import sys
import textwrap
from importlib.metadata import entry_points
from pathlib import Path

import pytest

import edge_landing
from edge_landing.cli.common import EXTRA_MODULES, CliParser, output_file, output_folder, run_cli
from edge_landing.runtime.core.errors import InputError

COMMANDS = ("edge-run", "edge-eval", "edge-calibrate", "edge-export", "edge-quantize", "edge-train", "edge-sim",
            "edge-bench")
ROOT = Path(__file__).resolve().parents[1]

# Makes the top-level modules named in argv[1] unimportable: a meta-path finder that says they are not there.
HIDE = textwrap.dedent("""
    import sys
    HIDE = set(sys.argv[1].split(",")) - {""}

    class HideExtras:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in HIDE:
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None

    sys.meta_path.insert(0, HideExtras())
""")
# Runs one console script (argv[2]) by its entry point, as the installed `edge-*` wrapper does.
RUNNER = HIDE + textwrap.dedent("""
    from importlib.metadata import entry_points
    (ep,) = [e for e in entry_points(group="console_scripts") if e.name == sys.argv[2]]
    sys.argv = sys.argv[2:]
    sys.exit(ep.load()())
""")


def run_command(name: str, *args: str, hide: tuple = (), cwd: Path | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-c", RUNNER, ",".join(hide), name, *map(str, args)], capture_output=True,
                          text=True, timeout=300, env=env, cwd=cwd)


def one_line_install_hint(proc: subprocess.CompletedProcess, name: str, extra: str) -> str:
    """The one error line; INFO log lines of what the command was doing (edge-run: "building the world")
    are not part of the error."""
    lines = [line for line in proc.stderr.strip().splitlines() if not line.startswith("INFO ")]
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"{name}: error: ") and f"pip install 'edge-landing[{extra}]'" in lines[0]
    return lines[0]


def test_every_command_is_an_installed_console_script():
    ours = {e.name: e.value for e in entry_points(group="console_scripts") if e.value.startswith("edge_landing.")}
    assert set(ours) == set(COMMANDS)


@pytest.mark.parametrize("name", COMMANDS)
def test_help_and_version_answer_with_exit_0(name):
    version = run_command(name, "--version")
    assert (version.returncode, version.stdout.strip(), version.stderr) == (0, f"edge-landing {edge_landing.__version__}", "")
    helped = run_command(name, "--help")
    assert helped.returncode == 0 and helped.stderr == ""
    for flag in ("--version", "--log-level"):
        assert flag in helped.stdout
    assert "--quiet" not in helped.stdout          # the old spelling works but is not advertised


@pytest.mark.parametrize("name,args,hide,extra", [
    ("edge-sim", ("{tmp}/scene", "--frames", "1"), ("embreex",), "sim"),
    ("edge-sim", ("{tmp}/scene", "--frames", "1"), ("tqdm",), "sim"),       # was a traceback: No module named 'tqdm'
    ("edge-export", ("--arch", "safeuav-small", "--out", "{tmp}/out/m.onnx"), ("torch",), "export"),
    ("edge-export", ("--arch", "safeuav-small", "--out", "{tmp}/out/m.onnx"), ("onnxscript",), "export"),
    ("edge-train", ("--arch", "edgenet", "--train", "{tmp}", "--out", "{tmp}/out"), ("torch",), "export"),
    ("edge-quantize", ("{tmp}/m.onnx", "--calib", "{tmp}", "--out", "{tmp}/out/q.onnx"), ("onnx",), "export"),
    ("edge-bench", ("--quick", "--out", "{tmp}/out"), ("torch",), "bench"),    # was a traceback: torch
    ("edge-bench", ("--quick", "--out", "{tmp}/out"), ("matplotlib",), "bench"),
    ("edge-run", ("--camera", "sim", "--max-frames", "1"), ("embreex",), "sim"),
])
def test_a_missing_extra_is_one_line_naming_the_install(tmp_path, name, args, hide, extra):
    proc = run_command(name, *(a.format(tmp=tmp_path) for a in args), hide=hide)
    line = one_line_install_hint(proc, name, extra)
    assert hide[0] in line
    assert not (tmp_path / "out").exists() and not (tmp_path / "scene").exists()   # stopped before any output
    if name != "edge-run":   # and --help still works without the extra
        assert run_command(name, "--help", hide=hide).returncode == 0


def test_landing_truth_without_the_sim_extra_is_one_line(tmp_path):
    log = tmp_path / "t.jsonl"
    log.write_text(json.dumps({"frame": 0, "valid": False, "ned_m": None}) + "\n")
    runner = HIDE + ("sys.argv = ['landing_truth', *sys.argv[2:]]\n"
                     "from edge_landing.benchmarks.landing_truth import main\nsys.exit(main())\n")
    proc = subprocess.run([sys.executable, "-c", runner, "embreex", str(log)], capture_output=True, text=True,
                          timeout=120)
    one_line_install_hint(proc, "landing_truth", "sim")


def test_a_lazy_import_deep_inside_is_still_one_line(capsys):
    def body(argv):
        raise ModuleNotFoundError("No module named 'matplotlib.pyplot'", name="matplotlib.pyplot")

    assert run_cli(body, []) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'matplotlib.pyplot' is not installed; pip install 'edge-landing[bench]'" in err[0]

    def other(argv):
        raise ModuleNotFoundError("No module named 'not_ours'", name="not_ours")

    with pytest.raises(ModuleNotFoundError):   # a bug of ours, not a missing extra: the traceback stays
        run_cli(other, [])


def test_the_extras_table_matches_pyproject():
    tomllib = pytest.importorskip("tomllib")
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    import_name = {"scikit-image": "skimage"}

    def modules(extra: str) -> set:
        out = set()
        for req in extras[extra]:
            dist = re.split(r"[\[<>=!~ ;]", req, maxsplit=1)[0]
            if dist == "edge-landing":
                for inner in re.search(r"\[(.*)\]", req).group(1).split(","):
                    out |= modules(inner.strip())
            else:
                out.add(import_name.get(dist, dist.replace("-", "_")))
        return out

    for extra, names in EXTRA_MODULES.items():
        assert set(names) == modules(extra), extra
    assert "torch==2.13.0" in extras["export"]              # pinned exactly: a looser pin pulls CUDA
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert not any(d.startswith("torch") for d in deps)     # never in the drone runtime


def test_log_level_and_the_one_no_progress_spelling():
    p = CliParser(prog="edge-x")
    p.add_no_progress()
    root = logging.getLogger()
    before = root.level
    try:
        assert p.parse_args(["--log-level", "warning"]).log_level == "WARNING"
        assert root.level == logging.WARNING
        assert p.parse_args([]).log_level == "INFO" and root.level == logging.INFO
    finally:
        root.setLevel(before)
    assert p.parse_args(["--no-progress"]).no_progress and p.parse_args(["--quiet"]).no_progress
    assert not p.parse_args([]).no_progress
    with pytest.raises(InputError, match="--log-level"):
        p.parse_args(["--log-level", "LOUD"])


def test_log_level_reaches_a_command():
    """--log-level WARNING silences the INFO lines edge-run logs (it builds its sim world at INFO)."""
    pytest.importorskip("embreex")
    loud = run_command("edge-run", "--max-frames", "1")
    quiet = run_command("edge-run", "--max-frames", "1", "--log-level", "warning")
    assert loud.returncode == 0 and quiet.returncode == 0, loud.stderr + quiet.stderr
    assert "INFO " in loud.stderr
    assert "INFO " not in quiet.stderr


def test_output_paths_are_settled_before_the_work(tmp_path):
    out = output_file(tmp_path / "a" / "b" / "x.json", "the --json file")
    assert out.parent.is_dir() and not out.exists()
    assert output_folder(tmp_path / "c" / "d", "the --out folder").is_dir()
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(InputError, match="cannot create the output folder"):
        output_file(blocker / "sub" / "x.json", "the --json file")
    with pytest.raises(InputError, match="exists and is not a folder"):
        output_folder(blocker, "the --out folder")
    with pytest.raises(InputError, match="is a folder"):
        output_file(tmp_path / "a", "the --json file")


def test_edge_eval_json_into_a_missing_folder_is_created_first(tmp_path, capsys):
    """The --json folder is created before the evaluation, and an impossible one fails before it (fast, and no
    figures computed for nothing)."""
    from edge_landing.cli.eval_cli import main as eval_main
    from edge_landing.runtime.models import default_model_path

    blocker = tmp_path / "file"
    blocker.write_text("")
    # the scene does not exist: the output path is checked first, so the error is about the output
    assert eval_main([str(default_model_path()), str(tmp_path / "nowhere"), "--json", str(blocker / "x.json")]) == 2
    assert "cannot create the output folder" in capsys.readouterr().err
    assert eval_main([str(default_model_path()), str(tmp_path / "nowhere"), "--json", str(tmp_path / "new" / "x.json")]) == 2
    assert "does not exist" in capsys.readouterr().err and (tmp_path / "new").is_dir()


def test_every_module_imports():
    """Every module of the package imports (a missing optional extra aside): an import error anywhere would
    reach the user as a traceback from the command that loads it."""
    import importlib
    import pkgutil

    extras = {m for names in EXTRA_MODULES.values() for m in names}
    for info in pkgutil.walk_packages(edge_landing.__path__, "edge_landing."):
        try:
            importlib.import_module(info.name)
        except ModuleNotFoundError as exc:
            if (exc.name or "").split(".")[0] not in extras:
                raise
